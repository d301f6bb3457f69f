#!/usr/bin/env bash
# The first GPU run: the GPU table in two commands of a few minutes each (experiments/gpu_run.py).
#
#   bash experiments/gpu_run.sh wheels   # here, with network: wheels the GPU machine may lack
#   bash experiments/gpu_run.sh 1        # on the GPU: Stage II ViT-S 518 bf16 vs official, MFU
#   bash experiments/gpu_run.sh 2        # on the GPU: Stage I 1024x768, irdepth predict 512x640
#   bash experiments/gpu_run.sh dry      # any machine: parts 1 and 2 on tiny shapes, float32
#
# Parts 1 and 2 need no network: they install this checkout with
# `pip install --no-deps --no-build-isolation -e .` (unless Python already imports it from here),
# then any of our dependencies missing there from experiments/gpu_wheels (made by `wheels`, not
# committed: pass it along with the working tree), and use the official Depth Anything V2 code
# from experiments/third_party/Depth-Anything-V2 when a checkout is there (not committed: carry
# the folder with the working tree; without it the reference is transformers' port). Results: experiments/results/gpu/{stage2_vits,stage1_predict}.json
# and gpu.md (the table; "not yet measured on a GPU" for a part not run). OUT=DIR writes elsewhere.
set -euo pipefail
cd "$(dirname "$0")/.."
part=${1:?usage: gpu_run.sh wheels|1|2|dry}
out=${OUT:-experiments/results/gpu}
wheels=experiments/gpu_wheels
# our dependencies the GPU image may lack (import name:wheel), and dm-pix's and matplotlib's
# (checked on 2026-12-08 against a Python 3.12 environment of only the image's packages)
needed="dm_pix:dm-pix chex:chex toolz:toolz matplotlib:matplotlib contourpy:contourpy cycler:cycler
fontTools:fonttools kiwisolver:kiwisolver pyparsing:pyparsing dateutil:python-dateutil PIL:pillow
tqdm:tqdm safetensors:safetensors"

if [[ $part == wheels ]]; then
  mkdir -p "$wheels"
  for pair in $needed; do
    pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 \
      --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 -d "$wheels" "${pair#*:}" >/dev/null
  done
  du -sh "$wheels"
  exit 0
fi

# both packages installed from this checkout? (asked from another folder: Python puts the current one on sys.path)
here=$(pwd -P)
if ! (cd / && python -c "import irdepth_jax as j, irdepth_experiments as e, os, sys
sys.exit([os.path.realpath(m.__path__[0]) for m in (j, e)] != sys.argv[1:])" \
      "$here/irdepth_jax" "$here/experiments") 2>/dev/null; then
  pip install -q --no-deps --no-build-isolation -e .
fi
missing=()
for pair in $needed; do
  python -c "import ${pair%%:*}" 2>/dev/null || missing+=("${pair#*:}")
done
if (( ${#missing[@]} )); then
  echo "installing from $wheels: ${missing[*]}"
  pip install -q --no-deps --no-index --find-links "$wheels" "${missing[@]}"
fi

case $part in
  1) python -m irdepth_experiments.gpu_run stage2 --out "$out" ;;
  2) python -m irdepth_experiments.gpu_run stage1 --out "$out" ;;
  dry) python -m irdepth_experiments.gpu_run stage2 --dry-run --out "$out"
       python -m irdepth_experiments.gpu_run stage1 --dry-run --out "$out" ;;
  *) echo "gpu_run.sh: unknown part '$part' (wheels, 1, 2 or dry)" >&2; exit 2 ;;
esac
