"""`irdepth export`: a Stage II model as one ONNX or StableHLO file."""

from __future__ import annotations

from irdepth_jax.cli.common import check_paths, compile_cache_flag
from irdepth_jax.errors import counted


def check(args) -> None:
    """CliError for a path given to export that does not exist."""
    check_paths(args, ("checkpoint", "sample"))


def add_parser(sub) -> None:
    """The `irdepth export` sub-command."""
    p = sub.add_parser("export", help="a Stage II model as one ONNX or StableHLO file",
                       description="Export raw (N, H, W) uint16 counts -> depth (N, H, W) "
                                   "float32 metres (the whole HSV pipeline, variables as "
                                   "constants) for one fixed input shape, and FILE.json beside "
                                   "it (shapes, dtypes, raw bit depth, max depth, class names, "
                                   "config). The artifact is checked against the JAX pipeline "
                                   "on sample frames and refused when they differ by more than "
                                   "1e-4 x max depth. onnx needs pip install "
                                   "'irdepth_jax[export]'.")
    p.add_argument("--checkpoint", required=True,
                   help="a Stage II workdir or checkpoint directory (stage2.preprocessing=hsv)")
    p.add_argument("--format", required=True, choices=("onnx", "stablehlo"),
                   help="onnx (jax2onnx, runs in onnxruntime) or stablehlo "
                        "(jax.export, runs with JAX alone)")
    p.add_argument("--height", type=int, required=True, help="frame height of the input")
    p.add_argument("--width", type=int, required=True, help="frame width of the input")
    p.add_argument("--batch", type=int, default=1, help="frames per call (default 1)")
    p.add_argument("--out", required=True, help="the artifact's file (FILE.json goes beside it)")
    p.add_argument("--sample", metavar="FILE",
                   help="raw frame file (HxW) for the export-time check (default: rendered "
                        "synthetic frames)")
    compile_cache_flag(p)
    p.set_defaults(func=run, check=check)


def run(args) -> int:
    """Writes the Stage II model as one ONNX / StableHLO file (+ FILE.json), checked against
    the JAX pipeline (`irdepth_jax.export`)."""
    from irdepth_jax.export import export_model, metadata_path

    meta = export_model(args.checkpoint, args.format, args.height, args.width, args.batch,
                        args.out, sample=args.sample)
    check = meta["check"]
    kind = "synthetic frame" if args.sample is None else "sample frame"
    print(f"max |{args.format} - JAX| = {check['max_abs_diff']:.3g} m on "
          f"{counted(check['frames'], kind)} (tolerance "
          f"{check['tolerance']:.3g} m)")
    print(f"wrote {args.out} and {metadata_path(args.out)}")
    return 0
