"""How much the MTSA-UNet's stale BatchNorm running averages cost the Stage I tables (a diagnostic).

    python experiments/bn_statistics.py --cache DIR   # ~20 s per model on 2 cores; writes
                                                      # experiments/results/bn_statistics.{md,json}

Every Stage I evaluation, and the HSV image Stage II reads, runs the MTSA-UNet in eval mode with
the BatchNorm running averages training left (`unet.bn_momentum` 0.9 at batch 8). For each Stage I
model of the committed tables 2, 3, 5 and 6 (their results.json name the runs, per row and seed;
the runs' weights are taken from the experiment cache `--cache`, where the tables trained them)
this measures PSNR, SSIM and mIoU, as `irdepth_jax.evaluators.evaluate_stage1` computes them, on
the first `--frames` frames of the tables' evaluation set, in eval mode:

* **stored**: with the stored running averages (checked against the run's own per-frame
  evaluation, `eval-*.npz`, on the same frames);
* **recomputed** ("precise BN"): with each BatchNorm's mean and variance recomputed exactly as the
  average over `--train-frames` training frames (the run's I-1 training frames, training
  augmentation, batches of the run's size) of the batch statistics, taken by train-mode passes
  at momentum 0; the weights are unchanged.

It decides no claim: it says how far the committed Stage I figures are from the same models'
figures with fresh statistics (docs/experiments.md, "BatchNorm statistics").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Iterable, Sequence

import numpy as np

from irdepth_experiments.cache import DEFAULT_CACHE, REPO, git_commit
from irdepth_experiments.runner import RESULTS

TABLES = ("table2_multitask_reconstruction", "table3_multitask_segmentation",
          "table5_rgg_reconstruction", "table6_rgg_segmentation")
MODES = ("stored", "recomputed")
LOADER_SEED = 1234


def stage1_runs(results: str = RESULTS, tables: Sequence[str] = TABLES) -> dict:
    """{'runs': {run name: {'rows': ['<table>: <row>', ...], 'seed'}}, 'train_data', 'eval_data'}:
    every Stage I run the `tables` in `results` read, and the training and evaluation data (paths
    relative to the cache) they share."""
    runs: dict[str, dict] = {}
    data = set()
    for table in tables:
        with open(os.path.join(results, table, "results.json")) as f:
            record = json.load(f)
        data.add((record["data"]["path"], record["eval_data"]["path"]))
        for row in record["rows"]:
            for seed, value in row["per_seed"].items():
                entry = runs.setdefault(value["run"], {"rows": [], "seed": int(seed)})
                entry["rows"].append(f"{table}: {row['label']}")
    if len(data) != 1:
        raise SystemExit(f"the tables were made on different data: {sorted(data)}")
    (train_data, eval_data), = data
    return {"runs": runs, "train_data": train_data, "eval_data": eval_data}


def recomputed_statistics(cfg, variables: dict, batches: Iterable[dict]) -> tuple[dict, int]:
    """(the MTSA-UNet's 'batch_stats' recomputed exactly, frames used): each BatchNorm's mean and
    variance as the mean over `batches` (dicts with 'raw14' (B, H, W) and optionally 'brightness'
    (B,), as a training loader yields them) of that batch's statistics, from train-mode passes at
    momentum 0 (the running average is then the batch's own); the weights are used unchanged."""
    import jax
    import jax.numpy as jnp

    from irdepth_jax.models.pipeline import unet_input
    from irdepth_jax.models.unet import MTSAUNet

    exact = MTSAUNet(dataclasses.replace(cfg.unet, bn_momentum=0.0))

    @jax.jit
    def batch_statistics(raw, brightness):
        _, updated = exact.apply(variables, unet_input(raw, cfg, brightness), train=True,
                                 mutable=["batch_stats"])
        return updated["batch_stats"]

    total, count, frames = None, 0, 0
    for batch in batches:
        brightness = batch.get("brightness")
        stats = batch_statistics(jnp.asarray(batch["raw14"]), None if brightness is None else jnp.asarray(brightness))
        total = stats if total is None else jax.tree.map(jnp.add, total, stats)
        count, frames = count + 1, frames + len(batch["raw14"])
    return jax.tree.map(lambda x: x / count, total), frames


def measure(run_dir: str, train_data: str, eval_data: str, frames: int, train_frames: int) -> dict:
    """{'stored': {psnr, ssim, miou}, 'recomputed': {...}, 'check': {...}} of the Stage I model in
    `run_dir` on the first `frames` test frames of `eval_data` (module docstring), both measured
    by `irdepth_jax.evaluators.evaluate_stage1` as the tables are."""
    from irdepth_jax.config import from_dict
    from irdepth_jax.data.source import DataSource, make_loader, phase_frames, resolve_raw_bits
    from irdepth_jax.evaluators import evaluate_stage1
    from irdepth_jax.runs.variables import load_stage1
    from irdepth_jax.train.parallel import DataParallel

    with open(os.path.join(run_dir, "config.json")) as f:
        cfg = from_dict(json.load(f))
    variables, _ = load_stage1(run_dir, cfg)

    source = DataSource(train_data, raw_bits=cfg.data.raw_bits)
    train_cfg = resolve_raw_bits(cfg, source)
    dataset, indices = phase_frames(source, "stage1_i1", train_cfg)
    batch_size = cfg.stage1.batch_size
    loader = make_loader(dataset, indices, batch_size, seed=LOADER_SEED, train=True, cfg=train_cfg)
    statistics, used = recomputed_statistics(
        cfg, variables, (batch for _, batch in zip(range(-(-train_frames // batch_size)), loader)))
    recomputed = {"params": variables["params"], "batch_stats": statistics}

    evaluation = DataSource(eval_data, raw_bits=cfg.data.raw_bits)
    eval_set, eval_indices = evaluation.frames("test")
    seg_set, seg_indices = evaluation.seg_frames("test")
    eval_indices, seg_indices = np.asarray(eval_indices)[:frames], np.asarray(seg_indices)[:frames]
    out: dict = {"train_frames": used, "frames": len(eval_indices)}
    per_frame = {}
    for mode, v in zip(MODES, (variables, recomputed)):
        metrics, per_frame[mode] = evaluate_stage1(cfg, v, eval_set, eval_indices, DataParallel("single"),
                                                   seg_frames=(seg_set, seg_indices), per_frame=True)
        out[mode] = {k: float(metrics["all"][k]) for k in ("psnr", "ssim", "miou")}
    stored = sorted(f for f in os.listdir(run_dir) if f.startswith("eval-") and f.endswith(".npz"))
    if stored:
        reference = np.load(os.path.join(run_dir, stored[0]))["psnr"][:len(eval_indices)]
        out["check"] = {"max_abs_psnr_vs_its_evaluation":
                        float(np.max(np.abs(reference - per_frame["stored"]["psnr"])))}
    return out


def write(record: dict, path: str) -> None:
    """`path`.json (the record) and `path`.md (a table per model and the means per row)."""
    with open(path + ".json", "w") as f:
        json.dump(record, f, indent=1)
    lines = ["# Stage I models: stored vs recomputed BatchNorm statistics", "",
             f"A diagnostic (`experiments/bn_statistics.py`; decides no claim). Command: `{record['command']}` "
             f"(git {record['git']}); the first {record['frames']} frames of the evaluation set, statistics "
             f"recomputed over {record['train_frames']} training frames. SYNTHETIC benchmark.", "",
             "| run | seed | rows | PSNR stored / recomputed | SSIM stored / recomputed | mIoU stored / recomputed |",
             "|---|---|---|---|---|---|"]
    for name, r in record["runs"].items():
        a, c = r["stored"], r["recomputed"]
        lines.append(f"| {name} | {r['seed']} | {'; '.join(r['rows'])} | {a['psnr']:.2f} / {c['psnr']:.2f} | "
                     f"{a['ssim']:.3f} / {c['ssim']:.3f} | {a['miou']:.3f} / {c['miou']:.3f} |")
    lines += ["", "Mean over seeds per table row:", "",
              "| row | PSNR stored / recomputed | SSIM stored / recomputed | mIoU stored / recomputed |",
              "|---|---|---|---|"]
    for row, runs in sorted(_by_row(record["runs"]).items()):
        means = {m: {k: np.mean([r[m][k] for r in runs]) for k in ("psnr", "ssim", "miou")} for m in MODES}
        lines.append(f"| {row} | {means['stored']['psnr']:.2f} / {means['recomputed']['psnr']:.2f} | "
                     f"{means['stored']['ssim']:.3f} / {means['recomputed']['ssim']:.3f} | "
                     f"{means['stored']['miou']:.3f} / {means['recomputed']['miou']:.3f} |")
    with open(path + ".md", "w") as f:
        f.write("\n".join(lines) + "\n")


def _by_row(runs: dict) -> dict[str, list[dict]]:
    rows: dict[str, list[dict]] = {}
    for r in runs.values():
        for row in r["rows"]:
            rows.setdefault(row, []).append(r)
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", default=DEFAULT_CACHE, help="the experiment cache the tables ran in")
    parser.add_argument("--frames", type=int, default=200, help="evaluation frames (the first N)")
    parser.add_argument("--train-frames", type=int, default=200, help="training frames for the statistics")
    parser.add_argument("--out", default=os.path.join(RESULTS, "bn_statistics"), help="output path, no suffix")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.train_frames < 1:
        parser.error("--frames and --train-frames must be at least 1")
    found = stage1_runs()
    missing = [n for n in found["runs"] if not os.path.isdir(os.path.join(args.cache, "runs", n, "checkpoints"))]
    if missing:
        raise SystemExit(f"{args.cache}: no weights of {', '.join(missing)} (train them with the tables' "
                         "commands first: docs/experiments.md)")
    record = {"command": ("python experiments/bn_statistics.py --cache <cache> "
                          f"--frames {args.frames} --train-frames {args.train_frames}"),
              "git": git_commit(), "frames": args.frames, "train_frames": args.train_frames, "runs": {}}
    for name, entry in found["runs"].items():
        start = time.time()
        result = measure(os.path.join(args.cache, "runs", name), os.path.join(args.cache, found["train_data"]),
                         os.path.join(args.cache, found["eval_data"]), args.frames, args.train_frames)
        record["train_frames"] = result.pop("train_frames")
        record["runs"][name] = entry | result
        print(f"{name} (seed {entry['seed']}): PSNR {result['stored']['psnr']:.2f} -> "
              f"{result['recomputed']['psnr']:.2f}, mIoU {result['stored']['miou']:.3f} -> "
              f"{result['recomputed']['miou']:.3f} ({time.time() - start:.0f} s)", flush=True)
    write(record, args.out)
    print(f"wrote {os.path.relpath(args.out, REPO)}.md and .json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
