#!/usr/bin/env bash
# The GPU table (README "Benchmarks"): one command on a CUDA machine, from the repository root,
# after `pip install -e '.[cuda,parity]'`:
#
#     OFFICIAL_REPO=PATH/TO/Depth-Anything-V2 bash experiments/bench_gpu.sh [OUT_DIR]
#
# 1. Stage II train step (SiLog + AdamW, metric head) at 518x518, bf16 compute / f32 params,
#    batch 8, ViT-S and ViT-L: ours vs the official code with torch AMP (bf16) on the same GPU
#    (each side in its own process, calls interleaved), images/s, ratio, MFU against the
#    measured bf16 8192^2 matmul peak; forward at 518x518 and 364x644.
# 2. Stage I, `paper` preset, at the paper's 1024x768 with accumulation 4 (batch 4): the real
#    `irdepth train stage1` on 64 synthetic frames, images/s from metrics.jsonl (median of steps
#    after the first, which compiles).
# Writes OUT_DIR (default experiments/results/gpu)/{bench_da_vits,bench_da_vitl}.json and
# stage1_1024x768.json, and prints each table.
set -euo pipefail
out=${1:-experiments/results/gpu}
mkdir -p "$out"
python -c "import jax; d = jax.devices()[0]; assert d.platform == 'gpu', f'no GPU: JAX sees {d}'; print(d.device_kind)"
official=()
if [[ -n "${OFFICIAL_REPO:-}" ]]; then official=(--official-repo "$OFFICIAL_REPO"); fi
for encoder in vits vitl; do
  python experiments/bench_depth_anything.py --encoder "$encoder" --dtype bfloat16 --amp \
    --sizes 518x518 364x644 --train-batch 8 --repeats 20 --warmup 3 --peak-size 8192 "${official[@]}" \
    --json "$out/bench_da_$encoder.json"
done
data=$(mktemp -d)/ms
irdepth synth --out "$data" --n 64 --labeled 32 --size 768x1024 --no-progress
irdepth train stage1 --preset paper --data "$data" --workdir "$data-run" --steps 30 --no-progress \
  --no-compile-cache log_every=1 eval_every=0 checkpoint_every=1000
python - "$data-run/metrics.jsonl" "$out/stage1_1024x768.json" <<'PY'
import json, statistics, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
result = {}
for phase in ("stage1_i1", "stage1_i2"):
    rates = [r["img_per_s"] for r in rows if r.get("stage") == phase and "img_per_s" in r][1:]
    result[phase] = {"images_per_s_median": statistics.median(rates), "steps": len(rates) + 1}
print(json.dumps(result, indent=1))
json.dump(result, open(sys.argv[2], "w"), indent=1)
PY
