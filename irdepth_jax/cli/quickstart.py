"""`irdepth quickstart`: synth -> Stage I -> Stage II -> eval on a tiny model."""

from __future__ import annotations

import os

from irdepth_jax.cli.common import CliError, checked_overrides, compile_cache_flag, load_config, progress_flag


def check(args) -> None:
    """CliError when --workdir holds files (the quickstart writes a new directory)."""
    if os.path.isdir(args.workdir) and os.listdir(args.workdir):
        raise CliError(f"--workdir {args.workdir} exists and is not empty; choose another directory")


def add_parser(sub) -> None:
    """The `irdepth quickstart` sub-command."""
    from irdepth_jax.config import available_presets

    p = sub.add_parser("quickstart", help="synth -> Stage I -> Stage II -> eval on a tiny model",
                       description="The whole pipeline on synthetic data with the tiny preset: "
                                   "render a dataset, train Stage I (I-1, I-2) and Stage II, "
                                   "print the test tables and the untrained -> trained change. "
                                   "A few minutes on a laptop CPU.")
    p.add_argument("--workdir", default="irdepth_quickstart",
                   help="new directory for data, runs and tables (default ./irdepth_quickstart)")
    p.add_argument("--preset", default="tiny", choices=available_presets(),
                   help="config preset, irdepth_jax/configs/NAME.py (default tiny)")
    p.add_argument("--devices", type=int, help="number of devices (default: all)")
    compile_cache_flag(p)
    progress_flag(p)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")
    p.set_defaults(func=run, check=check)


def run(args) -> int:
    """synth -> stage1 (I-1, I-2) -> stage2 -> eval (`workflow.train_and_evaluate`), with the
    untrained -> trained change."""
    from irdepth_jax.workflow import improvement_lines, train_and_evaluate

    work = args.workdir
    cfg = load_config(args.preset, None, checked_overrides(args.overrides))
    result = train_and_evaluate(cfg, work, devices=args.devices, progress=not args.no_progress)
    print(result["tables"])
    print("\n".join(improvement_lines(result)))
    print(f"quickstart finished in {result['seconds']:.0f} s; data, runs and tables "
          f"({work}/stage2/eval_test.md) are in {work}")
    print("\n".join(quickstart_next_steps(work, result["config"])))
    return 0


def quickstart_next_steps(work: str, cfg) -> list[str]:
    """What the quickstart made, and the commands that train a model for real frames."""
    d = cfg.data
    return [
        f"What it made: {work}/data ({d.num_frames} synthetic frames of {d.height}x{d.width}), "
        f"{work}/stage1 and {work}/stage2: a {cfg.name} model trained on synthetic frames, its "
        "depth network from random weights. It shows the pipeline runs; its depth on real "
        "camera frames means nothing (predict and eval warn so).",
        "Next, a model for real frames: MS2 (or a folder dataset, docs/data.md: --data "
        "FOLDER) and the released Depth Anything V2 weights "
        "(depth_anything_v2_metric_vkitti_vits.pth):",
        "  irdepth train stage1 --preset paper --data MS2_ROOT --workdir runs/s1 "
        "stage1.seg_labels=synthetic",
        "  irdepth train stage2 --preset paper --data MS2_ROOT --workdir runs/s2 "
        "--stage1-checkpoint runs/s1 depth.checkpoint=depth_anything_v2_metric_vkitti_vits.pth",
        "  irdepth eval --workdir runs/s2 --data MS2_ROOT --split test_day --stride 10",
        "  irdepth predict --checkpoint runs/s2 --out preds MS2_ROOT/sync_data/SEQ/thr/img_left"]
