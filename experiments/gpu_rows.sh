#!/usr/bin/env bash
# The network's GPU rows (issue 5) in one device call: `paper` forward at batch 1 and 16,
# float32 and bfloat16, and train steps, ours against the PyTorch peer on the same GPU
# (experiments/bench_model.py). Needs neither warp-lang nor mujoco, so nothing to carry but
# the peer, which lives outside the repository. Before the call, here:
#
#   mkdir -p .peer && cp ../shared/peers/torch_indoorbev.py .peer/ && echo /.peer/ >> .git/info/exclude
#
# then the device tool's run with command `bash experiments/gpu_rows.sh`, carry [".peer"],
# timeout_s 560. Rows run in priority order, each under its own time limit, so a slow
# compile costs one row, not the call; the log lands in $OUT/gpu_rows.log.
set -u
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
LOG="$OUT/gpu_rows.log"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
export INDOORBEV_PEER_DIR="${INDOORBEV_PEER_DIR:-$PWD/.peer}"
# JAX would take 75 % of the GPU up front and leave torch, in the same process, the rest;
# ours is measured from the compiled step's buffer assignment, which this does not change.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
PY=${PY:-python3}
ROW_LIMIT=${ROW_LIMIT:-85}

{
  date -u
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  "$PY" -c "import jax, flax, torch; print('jax', jax.__version__, jax.devices(), 'flax', flax.__version__, 'torch', torch.__version__, torch.cuda.is_available())"
} 2>&1 | tee -a "$LOG"

row() {
  echo "== bench_model.py $*" | tee -a "$LOG"
  timeout "$ROW_LIMIT" "$PY" experiments/bench_model.py --settle 0.02 "$@" 2>&1 \
    | grep -v -i "warning" | tee -a "$LOG"
  echo "== exit ${PIPESTATUS[0]}" | tee -a "$LOG"
}

row --preset paper --mode fwd --batch 1 --reps 20 --peer convT2
row --preset paper --mode fwd --batch 1 --reps 20 --peer convT2 --bf16
row --preset paper --mode fwd --batch 16 --reps 5 --peer convT2
row --preset paper --mode fwd --batch 16 --reps 5 --peer convT2 --bf16
row --preset paper --mode train --batch 2 --reps 10 --peer convT2
row --preset small --mode train --batch 4 --reps 20 --peer convT2
# The measured alternative to the paper's full-resolution cross-attention memory (masks stay
# full resolution): its speed on the GPU, interleaved with the paper setting.
row --preset paper --mode fwd --batch 1 --reps 20 --only jax --vs head.memory_stride=4
