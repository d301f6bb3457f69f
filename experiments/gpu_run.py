"""The GPU table in two short commands (driver of experiments/gpu_run.sh, which installs first).

    python experiments/gpu_run.py stage2 [--dry-run] [--out DIR]   # part 1
    python experiments/gpu_run.py stage1 [--dry-run] [--out DIR]   # part 2
    python experiments/gpu_run.py table [--out DIR]                # the table of what exists

Part 1, `stage2`: the Stage II train step (SiLog + AdamW, metric head) of Depth Anything V2 ViT-S
at 518x518, batch 8, ours in bfloat16 (float32 parameters) against the official code under torch
autocast (bfloat16) on the same GPU, each side in its own process, calls interleaved
(`bench_depth_anything`; the official code from `OFFICIAL_REPO`, experiments/third_party/
Depth-Anything-V2, which is not committed: place a checkout there and name the folder in the
device run's carry; without it the reference is transformers' port); images/s of each, and MFU:
XLA's FLOP count of the step over its time, as a share of the measured bfloat16 8192^3 matmul
peak (`bench_common.matmul_call`) and of the chip's spec sheet (`SPEC_BF16_TFLOPS`). Writes
OUT/stage2_vits.json.

Part 2, `stage1`: the Stage I train step of the `paper` MTSA-UNet at the paper's 1024x768
(H x W 768x1024), batch 4 (`bench_unet.setup_ours`: forward, Stage I loss, backward, AdaDelta on
a batch in memory), images/s; and `irdepth predict` (`predict.predict_files`: reading 16-bit PNGs,
the `paper` UNet + ViT-S in bfloat16, writing every output PNG) on 512x640 frames, frames/s at
batch 8 after a warm-up call that compiles. Writes OUT/stage1_predict.json.

`table` (run by both parts): OUT/gpu.md from the JSON files there; a part not run reads "not yet
measured on a GPU". --dry-run: the same code on tiny shapes, in bfloat16 with torch autocast as on
the GPU, on whatever device JAX has (about a minute on a CPU: tests/test_gpu_run.py); part 1 runs
ViT-S against the official code when its checkout is there (as the GPU run does), else the tiny
encoder against transformers' port. Its table says it is a dry run, not a GPU figure.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import tempfile
import time

# this process asks JAX for its device too: without this, it would take 75 % of the GPU's memory
# up front, away from the benchmark's worker processes (set before JAX's backend starts)
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "gpu")

SPEC_BF16_TFLOPS = {"H200": 989.4, "H100 PCIe": 756.0, "H100": 989.4, "A100": 312.0}
"""Dense bfloat16 tensor-core TFLOP/s of the spec sheets, by a substring of JAX's device_kind
(first match; the more specific names first)."""

NOT_MEASURED = "not yet measured on a GPU"

SHAPES = {
    # part 1: encoder, size, train batch, compute dtype, torch autocast, peak matmul N, repeats, warmup
    "stage2": {"gpu": ("vits", "518x518", 8, "bfloat16", True, 8192, 20, 3),
               "dry": ("tiny", "28x28", 1, "bfloat16", True, 64, 1, 0)},
    # part 2: preset, Stage I size, batch, repeats; predict size, frames, batch, Depth Anything dtype
    "stage1": {"gpu": ("paper", (768, 1024), 4, 10, (512, 640), 32, 8, "bfloat16"),
               "dry": ("tiny", (32, 48), 2, 1, (32, 48), 4, 2, "bfloat16")},
}


def spec_tflops(device_kind: str) -> float | None:
    """The spec-sheet dense bfloat16 TFLOP/s of a device (None: not in `SPEC_BF16_TFLOPS`)."""
    return next((v for k, v in SPEC_BF16_TFLOPS.items() if k in device_kind), None)


def _device() -> dict:
    device = jax.devices()[0]
    return {"platform": device.platform, "device_kind": device.device_kind, "jax": jax.__version__,
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}


def run_stage2(dry: bool) -> dict:
    """Part 1 (see the module docstring): the figures of `bench_depth_anything` and the MFUs."""
    from irdepth_experiments.bench_depth_anything import main as bench_depth_anything
    from irdepth_experiments.bench_depth_anything import official_code_present

    encoder, size, batch, dtype, amp, peak, repeats, warmup = SHAPES["stage2"]["dry" if dry else "gpu"]
    reference = "official" if official_code_present() else "transformers"
    if dry and reference == "official":
        encoder = "vits"  # the official code builds ViT-S up; the tiny encoder is transformers' port only
    if reference != "official" and not dry:
        print("gpu_run: no official Depth Anything V2 code at experiments/third_party/Depth-Anything-V2 "
              "(or $IRDEPTH_OFFICIAL_DA): timing against transformers' port instead")
    args = ["--encoder", encoder, "--dtype", dtype, "--sizes", "--train-size", size,
            "--train-batch", str(batch), "--references", reference, "--peak-size", str(peak),
            "--repeats", str(repeats), "--warmup", str(warmup), "--threads", str(os.cpu_count() or 1)]
    summary = bench_depth_anything(args + (["--amp"] if amp else []))
    (train,) = [r for r in summary["results"] if r["kind"] == "train_step"]
    flops = train["ours_gflops"] * train["ours_ms"] / 1e3  # GFLOP per step, XLA's count
    measured = summary["matmul_peak"]["xla_gflops"]
    spec = spec_tflops(_device()["device_kind"])
    result = {"part": "stage2", "dry_run": dry, **_device(), "encoder": encoder, "size": size, "batch": batch,
              "dtype": dtype, "torch_autocast_bf16": amp, "step_gflop": flops,
              "matmul_peak_tflops": measured / 1e3, "matmul_peak_n": peak, "spec_tflops": spec,
              "reference": reference, "ours_images_per_s": train["ours_images_per_s"],
              "reference_images_per_s": train["theirs_images_per_s"],
              "ours_over_reference_time": train["ours_over_theirs"], "bench_depth_anything": summary}
    for side, seconds in (("ours", train["ours_ms"] / 1e3), ("reference", train["theirs_ms"] / 1e3)):
        gflops = flops / seconds
        result[f"{side}_mfu_measured_peak"] = gflops / measured
        result[f"{side}_mfu_spec"] = gflops / (spec * 1e3) if spec else None
    return result


def _predict_rate(workdir: str, frames: str, out: str, batch: int) -> tuple[float, float]:
    """(frames/s, seconds) of one `predict_files` call over the frames in `frames`."""
    from irdepth_jax.predict import predict_files

    start = time.perf_counter()
    predict_files(workdir, [frames], out, batch_size=batch)
    seconds = time.perf_counter() - start
    return len(os.listdir(frames)) / seconds, seconds


def run_stage1(dry: bool) -> dict:
    """Part 2 (see the module docstring): Stage I step images/s and `irdepth predict` frames/s."""
    from irdepth_experiments.bench_common import wall_seconds
    from irdepth_experiments.bench_predict import make_model, write_frames
    from irdepth_experiments.bench_unet import setup_ours

    preset, size, batch, repeats, p_size, p_frames, p_batch, p_dtype = SHAPES["stage1"]["dry" if dry else "gpu"]
    result = {"part": "stage1", "dry_run": dry, **_device(), "preset": preset}
    calls, info = setup_ours(preset, True, size, batch, 64, train_only=True)
    calls["train"]()  # the first call after compiling also allocates
    seconds = [wall_seconds(calls["train"]) for _ in range(repeats)]
    result["stage1"] = {"size": list(size), "batch": batch, "compile_s": info["compile_train_s"],
                        "step_ms": [1e3 * s for s in seconds],
                        "images_per_s": batch / statistics.median(seconds),
                        "step_gflop": info["train_flops"] / 1e9}
    del calls

    with tempfile.TemporaryDirectory() as root:
        workdir, frames, warm = (os.path.join(root, name) for name in ("run", "frames", "warm"))
        cfg, _, _ = make_model(preset, p_dtype, workdir)
        write_frames(frames, p_frames, p_size)
        os.makedirs(warm)
        for name in sorted(os.listdir(frames))[:p_batch]:
            os.link(os.path.join(frames, name), os.path.join(warm, name))
        _, warm_s = _predict_rate(workdir, warm, os.path.join(root, "out_warm"), p_batch)
        rates = [_predict_rate(workdir, frames, os.path.join(root, f"out{k}"), p_batch)[0] for k in range(2)]
    result["predict"] = {"size": list(p_size), "frames": p_frames, "batch": p_batch, "depth_dtype": p_dtype,
                         "depth_encoder": cfg.depth.encoder,
                         "warmup_call_s": warm_s, "frames_per_s": statistics.median(rates), "frames_per_s_all": rates}
    return result


def _cell(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def write_table(out: str) -> str:
    """OUT/gpu.md from OUT/stage2_vits.json and OUT/stage1_predict.json (whichever exist); returns it."""
    parts = {}
    for part, name in (("stage2", "stage2_vits.json"), ("stage1", "stage1_predict.json")):
        path = os.path.join(out, name)
        if os.path.exists(path):
            with open(path) as f:
                parts[part] = json.load(f)
    lines = ["# GPU figures (experiments/gpu_run.sh)", ""]
    if any(p.get("dry_run") for p in parts.values()):
        lines += ["**DRY RUN on tiny shapes: these are no GPU figures.**", ""]
    for p in parts.values():
        lines.append(f"- {p['part']}: {p['device_kind']} ({p['platform']}), JAX {p['jax']}, {p['date']}")
    lines += ["", "| what | ours | official / reference | note |", "|---|---|---|---|"]
    s2 = parts.get("stage2")
    if s2:
        torch_dtype = "torch autocast bf16" if s2["torch_autocast_bf16"] else "float32"
        reference = {"official": "the official code", "transformers": "transformers' port"}[s2["reference"]]
        lines.append(f"| Stage II train step, {s2['encoder']} {s2['size']}, batch {s2['batch']}, {s2['dtype']} "
                     f"(vs {reference}, {torch_dtype}) | {s2['ours_images_per_s']:.1f} img/s | "
                     f"{s2['reference_images_per_s']:.1f} img/s | ours / reference time "
                     f"{s2['ours_over_reference_time']:.2f} |")
        lines.append(f"| MFU of that step vs the measured {s2['dtype']} {s2['matmul_peak_n']}^3 matmul peak "
                     f"({s2['matmul_peak_tflops']:.4g} TFLOP/s) "
                     f"| {100 * s2['ours_mfu_measured_peak']:.0f} % | {100 * s2['reference_mfu_measured_peak']:.0f} % "
                     f"| XLA's count, {s2['step_gflop']:.0f} GFLOP per step |")
        spec = s2["spec_tflops"]
        lines.append(f"| MFU vs the spec sheet ({_cell(spec, '.0f')} TFLOP/s dense bf16) | "
                     f"{_cell(s2['ours_mfu_spec'] and 100 * s2['ours_mfu_spec'], '.0f')} % | "
                     f"{_cell(s2['reference_mfu_spec'] and 100 * s2['reference_mfu_spec'], '.0f')} % | |")
    else:
        lines.append(f"| Stage II train step, ViT-S 518x518, batch 8, bf16 vs official (autocast); MFU | "
                     f"{NOT_MEASURED} | {NOT_MEASURED} | |")
    s1 = parts.get("stage1")
    if s1:
        st, pr = s1["stage1"], s1["predict"]
        lines.append(f"| Stage I train step, `{s1['preset']}`, {st['size'][0]}x{st['size'][1]}, batch "
                     f"{st['batch']} | {st['images_per_s']:.1f} img/s | - | compile {st['compile_s']:.0f} s |")
        lines.append(f"| `irdepth predict`, `{s1['preset']}` + {pr['depth_encoder']} {pr['depth_dtype']}, "
                     f"{pr['size'][0]}x"
                     f"{pr['size'][1]}, batch {pr['batch']} | {pr['frames_per_s']:.1f} frames/s | - | "
                     f"warm-up (compiling) call {pr['warmup_call_s']:.0f} s |")
    else:
        lines.append(f"| Stage I train step, `paper`, 768x1024, batch 4 | {NOT_MEASURED} | - | |")
        lines.append(f"| `irdepth predict`, `paper` + ViT-S bf16, 512x640, batch 8 | {NOT_MEASURED} | - | |")
    text = "\n".join(lines) + "\n"
    with open(os.path.join(out, "gpu.md"), "w") as f:
        f.write(text)
    return text


def main(argv=None) -> dict | None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("part", choices=("stage2", "stage1", "table"))
    parser.add_argument("--dry-run", action="store_true", help="tiny shapes, any device")
    parser.add_argument("--out", default=RESULTS, help="folder of the JSON files and gpu.md")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    result = None
    if args.part != "table":
        if not args.dry_run and jax.devices()[0].platform != "gpu":
            raise SystemExit(f"gpu_run: JAX sees no GPU ({jax.devices()[0]}); --dry-run runs on tiny shapes")
        result = (run_stage2 if args.part == "stage2" else run_stage1)(args.dry_run)
        name = "stage2_vits.json" if args.part == "stage2" else "stage1_predict.json"
        with open(os.path.join(args.out, name), "w") as f:
            json.dump(result, f, indent=1)
    print(write_table(args.out))
    return result


if __name__ == "__main__":
    main()
