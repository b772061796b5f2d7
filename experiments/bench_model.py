"""Benchmark the IndoorBEV network: compile time, forward and train-step latency, memory.

Ours (Flax) and the PyTorch peer (``../shared/peers/torch_indoorbev.py``, the speed and
memory bar) run in the same process, interleaved, on the same inputs (about 20k uniform
points per frame, 2 % padding); medians of several runs and the ratio peer / ours are
printed. The train step is forward + backward + AdamW with the peer's dummy loss (sum of
the mean squares of all outputs), so both sides do the same work.

Memory: for ours, XLA's buffer assignment of the compiled step (arguments + outputs +
temporaries, exact and load-independent); ``--only jax`` / ``--only torch`` run one side
alone so the printed peak RSS belongs to that side (one process per row).

The peer's upsampler defaults to bilinear x2 + 3x3 conv steps; ours is a dense layer +
depth-to-space per step, the same map as the peer's ``up_mode="convT2"``. Both peer modes
can be timed (``--peer``); the like-for-like ratio is against ``convT2``.

With ``INDOORBEV_RETAIN_MEMORY=1`` importing ``indoorbev_jax`` applies ``host_memory``: both
sides then reuse freed pages instead of faulting them in every step (the header says which);
without it, glibc's default.

The train step of ours compiles with ``xla_flags.train_compiler_options`` for its grid, as
``experiments/train.py`` compiles its step (YNNPACK dot fusions on small grids); the header
names the options, and ``--xla-vs`` variants set others on top.

Needs ``torch==2.13.0`` in the venv for the peer (benchmark-only, not a dependency)::

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_model.py --preset small --mode train \
        --batch 4 --peer convT2,bilinear_conv3
    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_model.py --preset paper --mode fwd \
        --batch 1 --reps 3 --peer convT2
    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_model.py --preset paper --mode train \
        --batch 2 --reps 2 --only jax --set head.remat=1 --set backbone.remat=1
    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_model.py --preset paper --mode train \
        --batch 1 --reps 2 --only jax --vs backbone.chunk_windows=81 --vs head.attention_chunk=3125
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import resource
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from indoorbev_jax import host_memory
from indoorbev_jax.cli import HelpFormatter, nonnegative_float, nonnegative_int, positive_int
from indoorbev_jax.config import Config, ConfigError, with_overrides
from indoorbev_jax.models import IndoorBEV
from indoorbev_jax.xla_flags import train_compiler_options

# INDOORBEV_PEER_DIR: where the peer lies when ../shared is not beside the checkout (a GPU
# machine gets only the repository, so experiments/gpu_rows.sh copies it in).
PEER_DIR = os.environ.get("INDOORBEV_PEER_DIR") or os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "peers"
)
N_POINTS = 20000


def make_inputs(cfg: Config, batch: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Uniform points in the workspace, the last 2 % of slots padding (as the peer does)."""
    rng = np.random.default_rng(seed)
    u = rng.random((batch, N_POINTS, 4), dtype=np.float32)
    lo = np.array([cfg.grid.x_range[0], cfg.grid.y_range[0], cfg.grid.z_range[0], 0.0])
    hi = np.array([cfg.grid.x_range[1], cfg.grid.y_range[1], cfg.grid.z_range[1], 1.0])
    pts = (lo + u * (hi - lo)).astype(np.float32)
    valid = np.ones((batch, N_POINTS), bool)
    valid[:, int(N_POINTS * 0.98) :] = False
    return pts, valid


def dummy_loss(preds) -> jax.Array:
    return sum(jnp.mean(jnp.square(x.astype(jnp.float32))) for x in jax.tree.leaves(preds))


def build_jax(cfg: Config, mode: str, batch: int, dtype, compiler_options=None):
    """Jitted step, compile seconds, XLA memory figure (bytes), parameter count and the XLA
    options it was compiled with.

    ``compiler_options``: XLA debug options for this compile only. A train step gets
    ``train_compiler_options`` for its grid underneath them, as ``train.py`` compiles it, so
    the figure is the one training sees; ``--xla-vs`` items override those.
    """
    if mode == "train":
        compiler_options = {**train_compiler_options(cfg.grid.shape), **(compiler_options or {})}
    model = IndoorBEV(cfg, dtype=dtype)
    pts, valid = (jnp.asarray(a) for a in make_inputs(cfg, batch))
    params = jax.jit(model.init)(jax.random.key(0), pts, valid)
    if mode == "fwd":

        def step(params, pts, valid):
            return dummy_loss(model.apply(params, pts, valid))

        args = (params, pts, valid)
        jitted = jax.jit(step)
    else:
        opt = optax.adamw(1e-4)

        def step(params, opt_state, pts, valid):
            loss, grads = jax.value_and_grad(lambda p: dummy_loss(model.apply(p, pts, valid)))(
                params
            )
            updates, opt_state = opt.update(grads, opt_state, params)
            return optax.apply_updates(params, updates), opt_state, loss

        args = (params, opt.init(params), pts, valid)
        jitted = jax.jit(step, donate_argnums=(0, 1))
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile(compiler_options or None)
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    mem_bytes = (
        mem.argument_size_in_bytes
        + mem.output_size_in_bytes
        - mem.alias_size_in_bytes
        + mem.temp_size_in_bytes
    )
    n_params = sum(x.size for x in jax.tree.leaves(params))
    state = {"args": args}

    def run():
        out = compiled(*state["args"])
        if mode == "train":
            state["args"] = (out[0], out[1], *state["args"][2:])
            out = out[2]
        jax.block_until_ready(out)

    return run, compile_s, mem_bytes, n_params, compiler_options


def build_peer(preset: str, mode: str, batch: int, up_mode: str, bf16: bool = False):
    """The peer's step (``torch_indoorbev.bench``'s step) on our inputs.

    On the GPU when JAX runs on one and torch sees CUDA (each timed run then ends with a
    ``torch.cuda.synchronize``). ``bf16`` is torch's autocast to bfloat16 on that device
    (CUDA, or the CPU, where oneDNN runs bf16 GEMMs on AMX / AVX-512 BF16), as ``--bf16`` is
    for ours.
    """
    import contextlib

    sys.path.insert(0, PEER_DIR)
    import torch
    import torch_indoorbev as peer

    # As many threads as XLA's CPU pool: the cores this process may run on (the 2-core
    # machines of the recorded rows gave 2, as the former fixed setting did).
    torch.set_num_threads(len(os.sched_getaffinity(0)))
    cuda = jax.devices()[0].platform == "gpu" and torch.cuda.is_available()
    # float32 matmuls on TF32 tensor cores, as XLA runs them on a GPU by default
    # (jax_default_matmul_precision); torch's default is full FP32, 4-8x slower there.
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True
    device = torch.device("cuda" if cuda else "cpu")
    model = peer.build(preset, up_mode=up_mode).to(device)
    cfg = Config.preset(preset)
    pts, valid = (torch.from_numpy(a).to(device) for a in make_inputs(cfg, batch))

    def autocast():
        if bf16:
            return torch.autocast(device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def sync():
        if cuda:
            torch.cuda.synchronize()

    if mode == "train":
        model.train()
        opt = torch.optim.AdamW(model.parameters(), lr=1e-4)

        def run():
            opt.zero_grad(set_to_none=True)
            with autocast():
                loss = peer.dummy_loss(model(pts, valid))
            loss.backward()
            opt.step()
            sync()
    else:
        model.eval()

        def run():
            with torch.inference_mode(), autocast():
                peer.dummy_loss(model(pts, valid))
            sync()

    return run, sum(p.numel() for p in model.parameters()), str(device)


# The peer's upsampler modes (torch_indoorbev's up_mode): anything else built the bilinear
# one under the name given.
PEER_UP_MODES = ("convT2", "bilinear_conv3")


def _peer_cuda():
    """torch where the peer runs on a GPU, else None."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available() or not torch.cuda.is_initialized():
        return None
    return torch


def _peer_gpu_peak_gib() -> float | None:
    """torch's peak CUDA allocation since the last reset, None off the GPU."""
    torch = _peer_cuda()
    return None if torch is None else torch.cuda.max_memory_allocated() / 2**30


def _reset_peer_gpu_peak() -> None:
    if (torch := _peer_cuda()) is not None:
        torch.cuda.reset_peak_memory_stats()


def _peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter
    )
    ap.add_argument(
        "--preset",
        default="small",
        choices=["tiny", "small", "paper"],
        help="config preset of both sides (the peer has no tiny)",
    )
    ap.add_argument(
        "--mode",
        default="train",
        choices=["fwd", "train"],
        help="fwd: the forward alone; train: forward, backward and AdamW step",
    )
    ap.add_argument("--batch", type=positive_int, default=4, help="frames per call")
    ap.add_argument(
        "--reps",
        type=nonnegative_int,
        default=5,
        help="timed runs of each side, interleaved (their median); 0: compile and memory only",
    )
    ap.add_argument(
        "--warmup",
        type=nonnegative_int,
        default=1,
        help="untimed runs of each side before the timed ones",
    )
    ap.add_argument("--set", action="append", default=[], help="config override a.b=v")
    ap.add_argument(
        "--bf16", action="store_true", help="bfloat16 computation (ours; the peer's by autocast)"
    )
    ap.add_argument(
        "--peer",
        default="convT2",
        help=f"comma list of peer up_modes ({', '.join(PEER_UP_MODES)}), or none",
    )
    ap.add_argument(
        "--only",
        default="both",
        choices=["both", "jax", "torch"],
        help="run one side alone (jax: ours, torch: the peer), so the peak RSS is its own",
    )
    ap.add_argument(
        "--vs",
        action="append",
        default=[],
        help="override a.b=v (on top of --set) for a second jax step timed interleaved with "
        "the first, e.g. the memory-lean settings against the plain ones",
    )
    ap.add_argument(
        "--xla-vs",
        action="append",
        default=[],
        help="XLA options 'name=value [name=value ...]' (e.g. "
        "xla_cpu_experimental_ynn_fusion_type=) for another jax step, same config, compiled in "
        "this process and timed interleaved with the first; repeat the flag for more variants",
    )
    ap.add_argument(
        "--settle",
        type=nonnegative_float,
        default=0.5,
        help="seconds idle before each timed run: torch's OpenMP workers and XLA's thread pool "
        "spin-wait after a step, and on 2 cores that spinning would be charged to the next side",
    )
    a = ap.parse_args(argv)
    xla_variants = [variant.split() for variant in a.xla_vs]
    bad = [item for items in xla_variants for item in items or [""] if "=" not in item]
    if bad:
        ap.error(f"--xla-vs expects NAME=VALUE, got {bad[0]!r}")

    peers = [] if a.only == "jax" or a.peer == "none" else a.peer.split(",")
    if a.only == "torch" and not peers:  # timed nothing, exit 0
        ap.error("--only torch with --peer none times nothing; name a peer up_mode")
    if unknown := [mode for mode in peers if mode not in PEER_UP_MODES]:
        ap.error(f"--peer: unknown up_mode {unknown[0]!r}; expected {', '.join(PEER_UP_MODES)}")
    # Refused before ours compiles (minutes for paper), not after.
    if peers and a.preset == "tiny":
        ap.error("the peer has no tiny preset; add --only jax")
    if peers and importlib.util.find_spec("torch") is None:
        ap.error("the PyTorch peer needs torch (pip install torch); or add --only jax")
    try:  # config.with_overrides: checked values, errors naming the item
        cfg = with_overrides(Config.preset(a.preset), a.set)
        vs_cfg = with_overrides(cfg, a.vs)
    except ConfigError as e:
        ap.error(str(e))
    label = f"{a.preset} {a.mode} B={a.batch}" + (" bf16" if a.bf16 else "")
    label += f" [{' '.join(a.set)}]" if a.set else ""
    if peers and (a.set or a.vs):
        print(f"note: --set / --vs change ours only; the peer is its {a.preset} preset as built")
    if peers and a.preset == "small":
        note = "the peer's small preset is another network than ours (full memory, no skips, "
        print(f"note: {note}no mask prior): only paper is like for like (docs/BENCHMARKS.md)")
    runners = {}
    if a.only != "torch":
        dtype = jnp.bfloat16 if a.bf16 else jnp.float32
        run, compile_s, mem, n, used = build_jax(cfg, a.mode, a.batch, dtype)
        runners["jax"] = run
        print(
            f"{label}: jax {jax.__version__} {jax.devices()[0].platform} params {n / 1e6:.3f} M, "
            f"XLA options {used or 'none'}, "
            f"compile {compile_s:.1f} s, XLA memory {mem / 2**30:.2f} GiB, "
            f"freed memory retained {'yes' if host_memory.retained else 'no'} (host_memory), "
            f"GLIBC_TUNABLES {os.environ.get('GLIBC_TUNABLES') or 'unset'}",
            flush=True,
        )
        variants = []  # (settings shown in the name, config, XLA options)
        if a.vs:
            variants.append((a.vs, vs_cfg, None))
        for items in xla_variants:
            options = {
                k: {"true": True, "false": False}.get(v, v)
                for k, v in (item.split("=", 1) for item in items)
            }
            variants.append((items, cfg, options))
        for shown, variant_cfg, variant_options in variants:
            run, compile_s, mem, _, used = build_jax(
                variant_cfg, a.mode, a.batch, dtype, variant_options
            )
            name = f"jax[{' '.join(shown)}]"
            runners[name] = run
            print(
                f"{label}: {name} XLA options {used or 'none'}, compile {compile_s:.1f} s, "
                f"XLA memory {mem / 2**30:.2f} GiB"
            )
    for up_mode in peers:
        run, n, device = build_peer(a.preset, a.mode, a.batch, up_mode, a.bf16)
        runners[f"torch[{up_mode}]"] = run
        print(f"{label}: torch[{up_mode}] params {n / 1e6:.3f} M on {device}", flush=True)

    if a.reps == 0:  # compile and memory figures only
        return
    for run in runners.values():
        for _ in range(a.warmup):
            run()
    times = {k: [] for k in runners}
    peer_peaks: dict[str, float] = {}  # per peer: the other peers' runs are not counted
    for _ in range(a.reps):  # interleaved: each rep runs every side once
        for k, run in runners.items():
            time.sleep(a.settle)
            _reset_peer_gpu_peak()
            t0 = time.perf_counter()
            run()
            times[k].append(time.perf_counter() - t0)
            if k.startswith("torch[") and (peak := _peer_gpu_peak_gib()) is not None:
                peer_peaks[k] = max(peer_peaks.get(k, 0.0), peak)
    med = {k: statistics.median(v) for k, v in times.items()}
    for k, v in times.items():
        runs = " ".join(f"{t * 1e3:.0f}" for t in v)
        extra = f"  ({1 / med[k]:.2f} steps/s)" if a.mode == "train" else ""
        print(f"{label}: {k:18s} median {med[k] * 1e3:9.1f} ms  runs [{runs}]{extra}")
    if "jax" in med:
        for k in med:
            if k != "jax":
                print(f"{label}: ratio {k} / jax = {med[k] / med['jax']:.2f}x")
    print(
        f"{label}: peak RSS of this process {_peak_rss_gib():.2f} GiB "
        f"(sides: {', '.join(runners)}), load average {os.getloadavg()[0]:.1f}"
    )
    for k, peak in peer_peaks.items():
        held = " (with the other peers' weights held)" if len(peer_peaks) > 1 else ""
        print(f"{label}: {k} peak CUDA memory allocated {peak:.2f} GiB{held}")


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "bench_model.py")  # Ctrl-C: one line and status 130
