"""The run directory of a training run or sweep: checkpoints, metrics log, run files.

``Checkpoints`` keeps orbax checkpoints (``checkpoints/`` and ``best/``), ``MetricsLog``
``metrics.jsonl`` and ``tb/``; ``check_run_kind`` and ``check_resume`` decide whether a
workdir may go on with a command's config and data, and ``holds_workdir`` locks it for one run.
"""

from __future__ import annotations

import collections
import functools
import hashlib
import json
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import numpy as np
import orbax.checkpoint as ocp

from indoorbev_jax import fileio
from indoorbev_jax.config import Config, config_diff

if TYPE_CHECKING:
    from indoorbev_jax.train import TrainState

log = logging.getLogger(__name__)

# Fields a resumed run may change: they set when to log, evaluate and checkpoint and how many
# checkpoints to keep, never what the parameters become. Not ``train.total_steps`` (the
# cosine schedule ends at it) nor ``train.eval_batches`` or ``inference.*`` (they change the
# validation scores that rank ``best/``).
RESUME_MAY_CHANGE = frozenset(
    {"train.log_every", "train.eval_every", "train.checkpoint_every", "train.keep_checkpoints"}
)


def _rank(value) -> float:
    """A validation metric as ``best/`` ranks it: NaN or missing (JSON null) is -inf."""
    return float(value) if value is not None and math.isfinite(value) else -math.inf


def _layout(tree) -> collections.Counter:
    """How many arrays of each (shape, dtype) a tree of arrays or array metadata holds."""
    leaves = [x for x in jax.tree.leaves(tree) if hasattr(x, "shape")]
    return collections.Counter((tuple(x.shape), str(np.dtype(x.dtype))) for x in leaves)


def _check_layout(folder: Path, stored, abstract) -> None:
    """Raises ``ValueError`` when checkpoint ``folder`` (its orbax metadata ``stored``) holds
    arrays of other shapes than ``abstract``, naming one that differs."""
    have, want = _layout(stored), _layout(abstract)
    if have == want:
        return
    extra = next(iter(have - want), None)
    missing = next(iter(want - have), None)
    raise ValueError(
        f"{folder}: holds {sum(have.values())} arrays, this run's state has "
        f"{sum(want.values())}, and they differ (e.g. stored {extra}, expected {missing}): "
        "the workdir holds another kind of run (a sweep's K stacked models, or a model of "
        "another config or code version). Nothing was changed; use another workdir"
    )


class _Unreadable(Exception):
    """A checkpoint orbax cannot restore (cut short, emptied, damaged)."""


def _restore_checked(manager: ocp.CheckpointManager, step: int, template: TrainState):
    """``manager``'s checkpoint ``step`` as ``template``'s tree: a layout other than the
    template's raises ``ValueError`` (``_check_layout``), any failure to read ``_Unreadable``."""
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, template)
    try:
        stored = manager.item_metadata(step)
    except Exception:  # noqa: BLE001 - no readable layout: the restore below decides
        stored = None
    if stored is not None:
        _check_layout(manager.directory / str(step), stored, abstract)
    try:
        return manager.restore(step, args=ocp.args.StandardRestore(abstract))
    except Exception as e:  # noqa: BLE001 - any unreadable checkpoint: the caller falls back
        raise _Unreadable(e) from e


class Checkpoints:
    """Orbax checkpoints: the latest ``keep`` under ``checkpoints/``, the best by a
    validation metric under ``best/``. Restoring falls back to older checkpoints, with a
    warning, when the latest is corrupt or partial."""

    def __init__(self, workdir: Path, keep: int, metric: str | None = "pq"):
        """``metric`` None: no ``best/`` (a sweep, which does not validate)."""
        self.metric = metric
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, enable_async_checkpointing=False)
        # One unnamed item, said up front: left to infer it, orbax reads the layout off the
        # newest step folder, and a partial one (empty, no default/) makes every step fail.
        single = ocp.StandardCheckpointHandler
        self.latest = ocp.CheckpointManager(
            Path(workdir).absolute() / "checkpoints", options=options, item_handlers=single()
        )
        self.unreadable: set[int] = set()  # steps restore() skipped: save() replaces them
        if metric is None:
            self.best = None
            return
        best_options = ocp.CheckpointManagerOptions(
            max_to_keep=1,
            # NaN (a validation split without objects, nothing predicted) ranks last: as a
            # number it replaced a better best/ for good.
            best_fn=lambda m: _rank(m[metric]),
            best_mode="max",
            enable_async_checkpointing=False,
        )
        self.best = ocp.CheckpointManager(
            Path(workdir).absolute() / "best", options=best_options, item_handlers=single()
        )

    def save(self, state: TrainState, step: int | None = None) -> None:
        """Saves ``state`` as ``step`` (default ``state.step``; a sweep's states hold K)."""
        step = int(state.step) if step is None else step
        if step in self.unreadable:  # a corrupt one the run fell back past: write it anew
            self.latest.delete(step)
            self.unreadable.discard(step)
        if step not in self.latest.all_steps():
            self.latest.save(step, args=ocp.args.StandardSave(state))

    def save_best(self, state: TrainState, metrics: dict) -> None:
        step = int(state.step)
        if step not in self.best.all_steps():
            self.best.save(
                step, args=ocp.args.StandardSave(state), metrics={self.metric: metrics[self.metric]}
            )

    def restore(self, template: TrainState) -> TrainState | None:
        """The newest readable checkpoint, or None when there is none. A checkpoint whose
        arrays are not the template's (another kind of run: a sweep's K stacked models, a
        model of another shape) raises ``ValueError``: falling back past it would delete it."""
        self.latest.reload()
        for step in sorted(self.latest.all_steps(), reverse=True):
            try:
                return _restore_checked(self.latest, step, template)
            except _Unreadable as e:
                log.warning("checkpoint %d is unreadable (%s); trying an older one", step, e)
                self.unreadable.add(step)
        return None

    def restore_best(self, template: TrainState) -> TrainState | None:
        """The best checkpoint, or None (a warning naming it) when there is none or it is
        unreadable; arrays not the template's raise ``ValueError``, as in ``restore``."""
        if self.best is None:
            return None
        # No ranked step when its metrics are gone (an emptied folder): best/ keeps one.
        step = self.best.best_step()
        step = max(self.best.all_steps(), default=None) if step is None else step
        if step is None:
            return None
        try:
            return _restore_checked(self.best, step, template)
        except _Unreadable as e:
            log.warning("%s is unreadable (%s)", self.best.directory / str(step), e)
            return None

    def close(self) -> None:
        self.latest.close()
        if self.best is not None:
            self.best.close()


def truncate_log(path: Path, step: int) -> None:
    """Keeps the records of a JSON-lines log up to ``step`` (a resume from that step).

    A last line that is not a JSON object (a write cut off by a kill) is dropped with a
    warning; such a line anywhere else is corruption and raises ``ValueError`` naming it.
    """
    lines = [
        (n, line)
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
        if line.strip()
    ]
    kept = []
    for k, (n, line) in enumerate(lines):
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            record = None
        if isinstance(record, dict):
            if record.get("step", 0) <= step:
                kept.append(line)
        elif k < len(lines) - 1:
            raise ValueError(f"{path}: line {n} is not a JSON object: {line[:80]!r}")
        else:
            log.warning("%s: line %d is cut off (an interrupted write); dropped", path, n)
    write_text_atomic(path, "".join(line + "\n" for line in kept))


class MetricsLog:
    """``metrics.jsonl`` plus TensorBoard; on resume, lines past the restored step go.

    A last line that is not a JSON object (a write cut off by a kill) is dropped with a
    warning; such a line anywhere else is corruption and raises ``ValueError`` naming it.
    """

    def __init__(self, workdir: Path, resume_step: int):
        self.path = Path(workdir) / "metrics.jsonl"
        self.tb = None
        if not writes_run_files():  # the other hosts of a multi-host run: process 0 logs
            return
        if self.path.exists():
            truncate_log(self.path, resume_step)
        from tensorboardX import SummaryWriter

        self.tb = SummaryWriter(str(Path(workdir) / "tb"), purge_step=resume_step + 1)

    def write(self, step: int, kind: str, values: dict) -> None:
        if self.tb is None:
            return
        # Undefined metrics (NaN) are written as null: strict JSON.
        clean = {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in values.items()
        }
        record = {"step": step, "kind": kind, **clean}
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        for name, value in values.items():
            if isinstance(value, int | float) and math.isfinite(value):
                self.tb.add_scalar(f"{kind}/{name}", value, step)
        self.tb.flush()

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def writes_run_files() -> bool:
    """Whether this process writes a run's own files (config.json, run.json, the metrics
    logs): the hosts of a multi-host run share the workdir, and each wrote every line of
    metrics.jsonl (orbax coordinates the checkpoints itself)."""
    return jax.process_index() == 0


def write_text_atomic(path: Path, text: str) -> None:
    fileio.atomic_write(Path(path), lambda tmp: tmp.write_text(text))


def _describe_source(data: str | None) -> str:
    return "the simulator" if data is None else data


SPLIT_FILES = ("train.txt", "val.txt")


def _elsewhere(kind: str) -> str:
    if kind == "sweep":
        return "sweep in another workdir"
    return "train in another workdir (--init-from this one to start from its parameters)"


def run_record(data: str | None, kind: str = "train") -> dict:
    """What ``run.json`` records: the kind of run ("train" or "sweep"), the data source (a
    folder, None for the simulator) and, for a folder, the sha256 of its split lists, so a
    resume that would read other frames, or the same ones in another order, is refused."""
    if data is None:
        return {"kind": kind, "data": None}
    splits = {}
    for name in SPLIT_FILES[:1] if kind == "sweep" else SPLIT_FILES:  # a sweep reads train only
        path = Path(data) / name
        splits[name] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
    return {"kind": kind, "data": data, "splits": splits}


# Files only one kind of run writes (also in workdirs from before run.json named the kind).
_KIND_FILES = {"train": ("metrics.jsonl", "best"), "sweep": ("hypers.json", "sweep.jsonl")}


def read_json(path: Path):
    """``path``'s JSON; a file that is not JSON is a ValueError naming it."""
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None


def read_config(path: Path) -> Config:
    """The config a run recorded in ``path`` (its config.json); errors name the file."""
    return Config.from_file_dict(read_json(path), path)


def read_record(path: Path, fields: tuple[str, ...] = ()) -> dict:
    """``path``'s JSON object, holding ``fields``; anything else is a ValueError naming it."""
    record = read_json(path)
    if not isinstance(record, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(record).__name__}")
    missing = [name for name in fields if name not in record]
    if missing:
        raise ValueError(f"{path}: has no field(s) {missing}")
    return record


def other_kind(workdir: Path, kind: str) -> str | None:
    """What says ``workdir`` holds the other kind of run than ``kind`` ("train" or
    "sweep"), or None: run.json's kind, or for a run.json from before it named one, the
    files only the other kind writes."""
    other = "sweep" if kind == "train" else "train"
    run_path = workdir / "run.json"
    recorded = read_record(run_path).get("kind") if run_path.exists() else None
    if recorded:
        return f"run.json says {other!r}" if recorded == other else None
    found = [name for name in _KIND_FILES[other] if (workdir / name).exists()]
    return f"it has {found[0]}" if found else None


def check_run_kind(workdir: Path, kind: str) -> None:
    """Raises ``ValueError`` when ``workdir`` holds the other kind of run (a training run
    for a sweep, or a sweep for training): with the same config and data the resume checks
    passed, and the first checkpoint save deleted the other run's checkpoints."""
    what = other_kind(workdir, kind)
    if what:
        held, verb = ("a sweep", "train") if kind == "train" else ("a training run", "sweep")
        raise ValueError(f"{workdir}: holds {held} ({what}); {verb} in another workdir")


def _has_checkpoint(workdir: Path) -> bool:
    """Whether ``workdir/checkpoints`` holds a finished step (orbax names them by step;
    an interrupted save is a ``<step>.orbax-checkpoint-tmp`` folder)."""
    folder = workdir / "checkpoints"
    return folder.is_dir() and any(p.name.isdigit() for p in folder.iterdir())


def check_resume(
    config_path: Path, run_path: Path, config: Config, data: str | None, kind: str = "train"
) -> None:
    """Raises ``ValueError`` unless the run (``kind`` "train" or "sweep") in
    ``config_path``'s folder may go on with ``config`` and ``data`` (a resolved folder, or
    None for the simulator): only fields in ``RESUME_MAY_CHANGE`` may differ (logged as a
    note), and the data source and the split lists it reads may not. A folder without
    ``config.json`` is a fresh run, unless it holds checkpoints."""
    if not config_path.exists():
        if _has_checkpoint(config_path.parent):  # their settings are unknown: not resumed
            raise ValueError(
                f"{config_path.parent}: holds checkpoints but no config.json, so what they "
                f"were trained with is unknown; put its config.json back, or {kind} in "
                "another workdir"
            )
        return
    diff = config_diff(read_config(config_path), config)
    lines = {k: f"  {k}: {a!r} -> {b!r}" for k, (a, b) in diff.items()}
    refused = [line for k, line in lines.items() if k not in RESUME_MAY_CHANGE]
    elsewhere = _elsewhere(kind)
    if refused:
        fresh = (
            "it has no checkpoint yet, so nothing was trained: remove its config.json and "
            f"run.json to start it afresh with these settings, or {elsewhere}"
            if not _has_checkpoint(config_path.parent)
            else elsewhere
        )
        raise ValueError(
            f"{config_path}: the workdir holds a run with another config (saved -> given):\n"
            + "\n".join(refused)
            + f"\nonly {', '.join(sorted(RESUME_MAY_CHANGE))} may change on resume; {fresh}"
        )
    if lines:
        log.info("note: resuming with (saved -> given):\n%s", "\n".join(lines.values()))
    if not run_path.exists():  # a run from before run.json was kept: nothing to compare
        return
    record = read_record(run_path, ("data",))
    saved = record["data"]
    if saved != data:
        raise ValueError(
            f"{run_path}: the run trained on {_describe_source(saved)}, this command gives "
            f"{_describe_source(data)} (if the same data moved, edit the data field of run.json)"
        )
    if data is None or "splits" not in record or not _has_checkpoint(run_path.parent):
        return  # the simulator, a run.json from before the digests, or nothing trained yet
    now = run_record(data, kind)["splits"]
    for name, digest in record["splits"].items():
        if name in now and now[name] != digest:
            raise ValueError(
                f"{run_path}: {Path(data) / name} changed since the run started (sha256 "
                f"{str(digest)[:12]} -> {str(now[name])[:12]}), so the resumed run would "
                f"read other frames or another order: restore the list, or {elsewhere}"
            )


def holds_workdir(run_fn):
    """Runs ``run_fn(config, workdir, ...)`` holding ``fileio.hold_folder``'s lock on
    ``workdir/.lock``: two runs started in one workdir both ran to the end, writing one
    metrics log and one set of checkpoints. Only process 0 of a multi-host run takes it
    (its hosts share the workdir)."""

    @functools.wraps(run_fn)
    def run(config, workdir, *args, **kwargs):
        workdir = Path(workdir)
        with fileio.hold_folder(workdir, "run", "workdir", take=writes_run_files()):
            return run_fn(config, workdir, *args, **kwargs)

    return run
