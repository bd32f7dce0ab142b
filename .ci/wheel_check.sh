#!/usr/bin/env bash
# The package stands alone: build a wheel of the checkout, install it into a fresh venv and run
# the commands that read the package's own files (recipes, shipped weights, benchmarks) from a
# folder outside the checkout, so nothing can come from the source tree.
#
# Usage: bash .ci/wheel_check.sh   (after `make install`: the dependencies come from .venv)
# Offline: the wheel is built without build isolation by .venv's setuptools; the fresh venv
# sees .venv's site-packages through a .pth file (its editable llrmpp_jax is not activated:
# .pth files inside a path added that way are not run), and the wheel goes in with --no-deps.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
py="$repo/.venv/bin/python"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
t0=$SECONDS

# Build from a copy of the files git knows (tracked, or untracked and not ignored): no build/
# or egg-info in the checkout, and no stray file decides what the wheel holds.
mkdir "$tmp/src"
(cd "$repo" && git ls-files -z --cached --others --exclude-standard \
  | while IFS= read -r -d '' f; do if [ -f "$f" ]; then printf '%s\0' "$f"; fi; done | xargs -0 cp --parents -t "$tmp/src")
"$py" -m pip wheel -q --no-deps --no-build-isolation -w "$tmp/dist" "$tmp/src"
wheel=$(ls "$tmp"/dist/llrmpp_jax-*.whl)
echo "built $(basename "$wheel") ($(du -k "$wheel" | cut -f1) KiB)"

"$py" -m venv "$tmp/venv"
site=$("$tmp/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_path("purelib"))')
"$py" -c 'import sysconfig; print(sysconfig.get_path("purelib"))' >"$site/_llrmpp_deps.pth"
"$tmp/venv/bin/python" -m pip install -q --no-deps --no-index "$wheel"

mkdir "$tmp/elsewhere" && cd "$tmp/elsewhere"
export PATH="$tmp/venv/bin:$PATH"
run() {  # run COMMAND...: print it and the first lines of its output; all of it on a failure
  local out
  echo "\$ $*"
  out=$("$@" 2>&1) || { echo "$out"; echo "FAILED: $*"; return 1; }
  printf '%s\n' "$out" | head -n "${LINES_SHOWN:-3}" || true
}
run python -c "import llrmpp_jax, os, sys; d = os.path.dirname(llrmpp_jax.__file__); \
print('llrmpp_jax from', d); sys.exit(not d.startswith('$tmp/venv/'))"
run llrmpp --help
run llrmpp demo --help
run llrmpp bench --help
run python -m llrmpp_jax.benchmarks.splat --help
run python -c "import llrmpp_jax.recipes as r; from llrmpp_jax.experiment import load_experiment; \
print('recipes:', r.recipe_names()); print([load_experiment(n).name for n in ('small', 'demo')])"
run python -c "from llrmpp_jax.experiment import load_experiment; from llrmpp_jax.pretrained import load_pretrained; \
cfg = load_pretrained('small', load_experiment('small').model)[1]; print('pretrained:small loads, width', cfg.backbone.dims)"
LINES_SHOWN=40 run llrmpp doctor
echo "wheel check passed in $((SECONDS - t0)) s"
