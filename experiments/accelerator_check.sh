#!/usr/bin/env bash
# One accelerator's speed checks in under 9 minutes, compiles included: `llrmpp doctor`,
# the paper's Table-1 cases (reconstruct at 16/32/64 inputs and render at 544x960,
# llrmpp_jax/benchmarks/paper.py), the stage-4 training step (cuDNN attention,
# llrmpp_jax/benchmarks/paper_step.py), then profiles of scaled-down programs (one reconstruct +
# render of 8 inputs; one stage-3 step, 8 + 8 views at 544x960) reduced to per-phase and top-30
# op tables (llrmpp_jax/profiling.py); last, the figures beside the paper's and the goals.
#
# Usage: bash experiments/accelerator_check.sh OUT_DIR
#        SCALE=cpu taskset -c 1 bash experiments/accelerator_check.sh OUT_DIR   # every part at tiny scale on a CPU
# Writes compact JSON only, never raw traces (at most 8 files, one folder deep):
#   OUT_DIR/log.txt                   environment, every part's output, exit status and seconds
#   OUT_DIR/model/bench_model.json    Table-1 cases (model/bench.json: `llrmpp bench`'s summary)
#   OUT_DIR/step/bench_paper_step.json  the stage-4 step (step/bench.json likewise)
#   OUT_DIR/profile_model.json        profile of one reconstruct + render (Markdown in log.txt)
#   OUT_DIR/profile_step.json         profile of one stage-3 step (Markdown in log.txt)
# Parts, in this order, and their time limits in seconds (override one with LIMIT_<PART>=S):
#   environment 30, doctor 60, model 200, profile_model 100, step 220, profile_step 170.
# Each part runs under `timeout` in its own process group, so one that hangs or fails leaves
# the others' results; together they stop at TOTAL_S (default 520 s: a part gets at most what
# is left, one with under 20 s left is skipped), then the summary (at most 30 s) prints the
# comparison with the paper. PARTS lists the parts to run, in order (default all, as above):
# a part cut short reruns alone on the still-warm machine, e.g. PARTS=profile_step.
# Expected on an H200 (experiments/README.md): doctor ~30 s; the stage-4 step ~170 s (compile
# ~85 s, then two steps of ~28 s; parameters are built on the host CPU, where the GPU spent
# 52 s compiling their init). The reconstruct, render and profile times are what this measures;
# the estimate for all parts is ~8.5-9.5 minutes, so profile_step, last, is the likeliest cut.
# On the lent machines carry .whl (wheels of OpenImageIO, tensorboardX and plyfile; installed
# into /tmp/site first). PYTHON overrides the interpreter. At paper scale XLA_FLAGS defaults to
# --xla_gpu_enable_triton_gemm=false (cuBLAS GEMMs only: the GEMM autotuning of the compiles
# stays short, as in the 27.8 s stage-4 measurement) and a persistent compilation cache
# (JAX_COMPILATION_CACHE_DIR, default /tmp/llrmpp_jax_cache, outside OUT_DIR) makes the step's
# memory-analysis compile a cache hit.
set -u
out=${1:?usage: bash experiments/accelerator_check.sh OUT_DIR}
py=${PYTHON:-python3}
scale=${SCALE:-paper}
parts=${PARTS:-environment doctor model profile_model step profile_step}
total=${TOTAL_S:-520}
mkdir -p "$out"
log="$out/log.txt"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.95} \
  JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/llrmpp_jax_cache} \
  JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0 JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES=0
if [ "$scale" = paper ]; then export XLA_FLAGS=${XLA_FLAGS:---xla_gpu_enable_triton_gemm=false}; fi

limit_of() {  # limit_of PART: its time limit (LIMIT_<PART> or the default above)
  local var="LIMIT_${1^^}"
  case $1 in
    environment) echo "${!var:-30}" ;; doctor) echo "${!var:-60}" ;; model) echo "${!var:-200}" ;;
    step) echo "${!var:-220}" ;; profile_model) echo "${!var:-100}" ;; profile_step) echo "${!var:-170}" ;;
    *) echo 0 ;;
  esac
}

# The measured figures beside the paper's A100 figures and the per-chip goals (argument: OUT_DIR).
read -r -d '' summary_py <<'EOF'
import json, os, sys
from llrmpp_jax.benchmarks.paper import paper_comparison
def load(path):
    path = os.path.join(sys.argv[1], path)
    return json.load(open(path)) if os.path.exists(path) else None
table1, step = load("model/bench_model.json"), load("step/bench_paper_step.json")
case = next(iter((step or {}).get("cases", {}).values()), None)
print(paper_comparison(table1, case))
rows = (table1 or {}).get("reconstruct", []) + ([table1["render"]] if table1 and table1.get("render") else [])
for row in rows + ([case] if case and "step_s_median" in case else []):
    what = f"views {row['views']}" if "views" in row else "render" if "fps" in row else "step"
    print(f"{what}: {row.get('run_s_median', row.get('step_s_median')):.3f} s, compile {row['compile_s']:.1f} s, "
          f"{row['tflops_per_s']:.2f} TFLOP/s, peak fraction {row['peak_fraction']}, "
          f"device peak bytes {row.get('device_peak_bytes', row.get('device_peak_bytes_in_use'))}")
EOF

run_part() {  # run_part NAME COMMAND...: within its limit and what is left of TOTAL_S; log it
  local name=$1; shift
  local limit left
  limit=$(limit_of "$name"); left=$((total - SECONDS))
  if [ "$left" -lt "$limit" ]; then limit=$left; fi
  if [ "$limit" -lt 20 ]; then
    echo "=== $name: skipped, ${left}s of TOTAL_S=${total} left" | tee -a "$log"; return
  fi
  echo "=== $name ($(date -u +%T), limit ${limit}s)" >>"$log"
  local t0=$SECONDS
  timeout -k 10 "$limit" "$@" >>"$log" 2>&1
  echo "=== $name: exit $? after $((SECONDS - t0)) s" | tee -a "$log"
}

echo "=== accelerator_check.sh: scale $scale, parts: $parts, TOTAL_S $total" >"$log"
# Packages the lent machines lack (OpenImageIO, which the trainer's imports need, tensorboardX,
# plyfile) travel as Python 3.12 wheels in .whl/ (carry it; experiments/accelerator_small.sh
# says how to make them).
if [ -d .whl ]; then
  "$py" -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl >>"$log" 2>&1 \
    && export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
for part in $parts; do
  case $part in
    environment) run_part environment bash -c 'nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv \
      || echo "no nvidia-smi"; "$0" -c "import json; from llrmpp_jax.benchmarks.measure import environment as e; print(json.dumps(e()))"' \
      "$py" ;;
    doctor) run_part doctor "$py" -m llrmpp_jax.cli doctor ;;
    model) run_part model "$py" -m llrmpp_jax.cli bench --scale "$scale" --only model --out "$out/model" ;;
    step) run_part step "$py" -m llrmpp_jax.cli bench --scale "$scale" --only paper_step --out "$out/step" ;;
    profile_model) run_part profile_model "$py" -m llrmpp_jax.benchmarks.model --scale "$scale" --profile \
      --out "$out/profile_model.json" ;;
    profile_step) run_part profile_step "$py" -m llrmpp_jax.benchmarks.paper_step --scale "$scale" --profile \
      --out "$out/profile_step.json" ;;
    *) echo "=== $part: unknown part, expected some of: environment doctor model profile_model step profile_step" \
      | tee -a "$log" ;;
  esac
done
echo "=== summary ($SECONDS s after the start)" >>"$log"
timeout 30 "$py" -c "$summary_py" "$out" 2>&1 | tee -a "$log"
echo "=== done after $SECONDS s" | tee -a "$log"
