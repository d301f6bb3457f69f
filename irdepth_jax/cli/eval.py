"""`irdepth eval`: the metric tables of a trained run on a split."""

from __future__ import annotations

import sys

from irdepth_jax.cli.common import check_out_dir, check_paths, checked_overrides, compile_cache_flag, strict_flag


def check(args) -> None:
    """CliError for an --out that is a file or a path that does not exist."""
    check_out_dir(args.out)
    check_paths(args, ("checkpoint", "workdir", "data"))


def add_parser(sub) -> None:
    """The `irdepth eval` sub-command."""
    from irdepth_jax.config import MS2_DEPTH_LABELS

    p = sub.add_parser("eval", help="metric tables of a trained run (Markdown + JSON)",
                       description="Evaluate a run on a split: depth d1 d2 d3 AbsRel SqRel RMSE "
                                   "RMSE-log log10 SiLog (Stage II) and PSNR SSIM entropy mIoU "
                                   "(Stage I), overall and per condition.")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--workdir", help="a run directory (its latest stage is evaluated)")
    where.add_argument("--checkpoint", help="a checkpoint directory")
    p.add_argument("--data", required=True, help="dataset directory (folder format or MS2)")
    p.add_argument("--format", default="auto", choices=("auto", "folder", "ms2"),
                   help="dataset format (default: auto-detect)")
    p.add_argument("--split", default="test", help="split to evaluate (default test)")
    strict_flag(p)
    p.add_argument("--stride", type=int, default=1, metavar="N",
                   help="evaluate frames[0:-1:N] of the split's frame list (all sequences "
                        "concatenated), as the official MS2 loader does; the MS2 test protocol "
                        "is --stride 10 (default 1: every frame)")
    p.add_argument("--align", default="auto", choices=("auto", "none", "median", "scale_shift"),
                   help="per-image alignment of the predicted depth before the metrics: "
                        "median scaling or least-squares scale and shift (default auto: none "
                        "for a metric model, median for a relative one, depth.metric=false, "
                        "which refuses none); predictions are then clamped to "
                        "[data.min_depth, data.max_depth]")
    p.add_argument("--gt", metavar="NAME", choices=tuple(MS2_DEPTH_LABELS),
                   help="MS2: the depth label version to compare with: "
                        f"{', '.join(MS2_DEPTH_LABELS)} (default depth_filtered; published "
                        "numbers differ by about 0.04 AbsRel between them)")
    p.add_argument("--out", help="where eval_<split>.md / .json go (default: the run directory)")
    compile_cache_flag(p)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                   help="config overrides (e.g. data.max_depth=50)")
    p.set_defaults(func=run, check=check)


def run(args) -> int:
    from irdepth_jax.evaluate import evaluate_run, nonfinite_warning

    path = args.checkpoint or args.workdir
    result = evaluate_run(path, args.data, args.split, args.format, out_dir=args.out,
                          overrides=checked_overrides(args.overrides), stride=args.stride,
                          align=args.align,
                          strict=args.strict, gt=args.gt)
    print(result["markdown"])
    for line in result["warnings"]:
        print(f"irdepth: WARNING: {line}", file=sys.stderr)
    warning = nonfinite_warning(result)
    if warning:
        print(f"irdepth: WARNING: {warning}", file=sys.stderr)
    out = args.out or path
    print(f"tables written to {out}/eval_{args.split}.md and .json")
    return 0
