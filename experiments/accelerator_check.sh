#!/usr/bin/env bash
# One accelerator's checks, in about 20 minutes: the paper's stage-4 training step executed
# with the cuDNN attention kernel, then with the blockwise kernel (experiments/bench_paper_step.py),
# `llrmpp doctor` at the device's default matmul precision and at "highest", and
# `llrmpp bench --scale paper --only attention`.
#
# Usage: bash experiments/accelerator_check.sh OUT_DIR
# (where one command may run at most 10 minutes, lower PAPER_STEP_TIMEOUT or run the parts
# below one by one)
# Writes OUT_DIR/log.txt (environment and every command's output), OUT_DIR/paper_step_cudnn.json,
# OUT_DIR/paper_step_blockwise.json and OUT_DIR/bench/ (bench.json, bench_attention.json).
# Each part has its own time limit, so one that hangs or fails leaves the others' results.
# PYTHON overrides the interpreter; BLOCKWISE_BLOCK the blockwise kernel's "Q,K" blocks for
# the stage-4 step (default 2048,2048: the config's 512 makes 510 x 510 sequential blocks
# per attention call at 261k tokens). PAPER_STEP_TIMEOUT: seconds per kernel (default 480; on
# an H200 each kernel took ~205 s from launch to its second step's end, experiments/README.md).
# A persistent compilation cache makes the bench's memory_analysis() compile a cache hit.
set -u
out=${1:?usage: bash experiments/accelerator_check.sh OUT_DIR}
py=${PYTHON:-python3}
mkdir -p "$out"
log="$out/log.txt"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.95} \
  JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-$out/jax_cache} \
  JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0 JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES=0
part() {  # part SECONDS NAME COMMAND...: run with a time limit, log its output and exit status
  local limit=$1 name=$2; shift 2
  echo "=== $name ($(date -u +%T), limit ${limit}s)" >>"$log"
  local t0=$SECONDS
  timeout "$limit" "$@" >>"$log" 2>&1
  echo "=== $name: exit $? after $((SECONDS - t0)) s" >>"$log"
}
part 20 environment bash -c "nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; $py -c 'import jax, flax, optax; print(\"jax\", jax.__version__, \"flax\", flax.__version__, \"optax\", optax.__version__, jax.devices())'"
limit=${PAPER_STEP_TIMEOUT:-480}
part $((limit + 10)) paper_step_cudnn "$py" experiments/bench_paper_step.py --impls cudnn --steps 2 --timeout "$limit" \
  --out "$out/paper_step_cudnn.json"
part 120 doctor "$py" -m llrmpp_jax.cli doctor
part 90 doctor_highest env JAX_DEFAULT_MATMUL_PRECISION=highest "$py" -m llrmpp_jax.cli doctor
part 100 bench_attention "$py" -m llrmpp_jax.cli bench --scale paper --only attention --out "$out/bench"
part $((limit + 10)) paper_step_blockwise "$py" experiments/bench_paper_step.py --impls blockwise --steps 1 --timeout "$limit" \
  --block "${BLOCKWISE_BLOCK:-2048,2048}" --out "$out/paper_step_blockwise.json"
