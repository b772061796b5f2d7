#!/usr/bin/env bash
# Issue 9: the `paper` preset trained and evaluated on a lent GPU, in one device call.
# Before the call, here: `bash experiments/gpu_wheels.sh` (the wheels the image lacks, into
# .whl/). Then the device tool's run with command `bash experiments/gpu_paper.sh`, carry
# [".whl"], timeout_s 590. The simulator runs on the GPU with its pure-JAX caster (no
# warp-lang there). Two stages, each under its own time limit so one slow stage costs only
# itself: train (`paper`, killed at TRAIN_LIMIT s if not done; checkpoints every CKPT steps,
# so a kill loses at most CKPT steps, and the run resumes from its workdir) -> eval (the
# held-out test split, from the run's latest checkpoint). Dry run here, on the CPU, with
# Warp hidden: NO_WHEELS=1 PY=.venv/bin/python PYTHONPATH=DIR (DIR/sitecustomize.py holding
# `import sys; sys.modules["warp"] = None`) STEPS=2 BATCH=1 EVAL_FRAMES=4 EVAL_BATCH=4.
# Everything lands in $OUT: gpu_paper.log, metrics.jsonl, config.json, paper_test.json.
# VIEWS_FRAMES=N (default 0: skipped) adds a third stage: the same checkpoint on N test frames
# with the 8 test-time views (`--views all`, batch VIEWS_BATCH = 2 frames = 16 forwards),
# into paper_test_views.json.
set -u
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
LOG="$OUT/gpu_paper.log"
PY=${PY:-python3}
STEPS=${STEPS:-3000}
BATCH=${BATCH:-8}
CKPT=${CKPT:-100}
TRAIN_LIMIT=${TRAIN_LIMIT:-330}
EVAL_LIMIT=${EVAL_LIMIT:-110}
EVAL_FRAMES=${EVAL_FRAMES:-512}
EVAL_BATCH=${EVAL_BATCH:-8}  # the CPU rows' batch: eval_sim's frames depend on --batch
VIEWS_FRAMES=${VIEWS_FRAMES:-0}
VIEWS_BATCH=${VIEWS_BATCH:-2}
RUN=${RUN:-/tmp/runs/paper_gpu}

# Our two packages without installing them: src/ holds indoorbev_jax, sim/ is indoorbev_sim.
mkdir -p /tmp/pkgs && ln -sfn "$PWD/sim" /tmp/pkgs/indoorbev_sim
if [ -z "${NO_WHEELS:-}" ] && ls .whl/*.whl >/dev/null 2>&1; then  # NO_WHEELS=1: a local dry run
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
fi
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD/src:/tmp/pkgs:/tmp/site${PYTHONPATH:+:$PYTHONPATH}"

stage() {  # stage NAME LIMIT CMD...: run CMD under LIMIT seconds, log its output and exit code
  local name=$1 limit=$2
  shift 2
  echo "== $name ($(date -u +%H:%M:%S), limit ${limit} s): $*" | tee -a "$LOG"
  timeout "$limit" "$@" 2>&1 | grep --line-buffered -v -i "warning" | tee -a "$LOG"
  echo "== $name exit ${PIPESTATUS[0]} ($(date -u +%H:%M:%S))" | tee -a "$LOG"
}

{
  date -u
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  "$PY" -c "import jax, flax, optax, mujoco; from mujoco import mjx; print('jax', jax.__version__, jax.devices(), 'flax', flax.__version__, 'optax', optax.__version__, 'mujoco', mujoco.__version__)"
} 2>&1 | tee -a "$LOG"

stage train "$TRAIN_LIMIT" "$PY" experiments/train.py --preset paper --workdir "$RUN" \
  --steps "$STEPS" --batch-size "$BATCH" --eval-every "$STEPS" --checkpoint-every "$CKPT" \
  --bfloat16 --no-progress
cp "$RUN/metrics.jsonl" "$RUN/config.json" "$OUT/" 2>/dev/null
stage eval "$EVAL_LIMIT" "$PY" experiments/eval_sim.py --model "$RUN" --frames "$EVAL_FRAMES" \
  --batch "$EVAL_BATCH" --score-threshold 0.3,0.8 --json "$OUT/paper_test.json" --no-progress
if [ "$VIEWS_FRAMES" -gt 0 ]; then
  stage views "$EVAL_LIMIT" "$PY" experiments/eval_sim.py --model "$RUN" --frames "$VIEWS_FRAMES" \
    --batch "$VIEWS_BATCH" --score-threshold 0.3,0.8 --views all \
    --json "$OUT/paper_test_views.json" --no-progress
fi
