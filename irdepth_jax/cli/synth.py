"""`irdepth synth`: render a synthetic LWIR dataset in the folder format."""

from __future__ import annotations

import os

from irdepth_jax.cli.common import CliError, parse_size, progress_flag
from irdepth_jax.errors import counted


def check(args) -> None:
    """CliError for `irdepth synth` counts that do not go together or an --out that holds
    files (without --overwrite); --labeled defaults to half of --n."""
    if args.n < 1:
        raise CliError(f"--n {args.n}: render at least one frame")
    if args.labeled is None:
        args.labeled = args.n // 2
    if not 0 <= args.labeled <= args.n:
        raise CliError(f"--labeled {args.labeled}: choose 0 to --n ({args.n})")
    if os.path.isdir(args.out) and os.listdir(args.out) and not args.overwrite:
        raise CliError(f"--out {args.out}: directory exists and is not empty; choose another "
                       "path, or pass --overwrite to replace the dataset")


def add_parser(sub) -> None:
    """The `irdepth synth` sub-command."""
    p = sub.add_parser("synth", help="render a synthetic LWIR dataset (our folder format)",
                       description="Render procedural LWIR street scenes (raw 14-bit, 8-bit, RGB, "
                                   "LiDAR-like depth, labels) into a folder dataset.")
    p.add_argument("--out", required=True, help="dataset directory (absent or empty)")
    p.add_argument("--n", type=int, default=96, help="number of frames (default 96)")
    p.add_argument("--labeled", type=int, default=None,
                   help="frames with segmentation labels (default: half of --n)")
    p.add_argument("--size", type=parse_size, default=(64, 80), metavar="HxW",
                   help="frame size, e.g. 256x320 (default 64x80)")
    p.add_argument("--seed", type=int, default=0, help="dataset seed (default 0)")
    p.add_argument("--scenes", choices=("street", "varied"), default="street",
                   help="scene distribution: 'street' (one straight street, a level camera at "
                        "~1.5 m; the default and what the committed results used) or 'varied' "
                        "(camera height 1.3-1.7 m, horizon row and roll per frame, one field of "
                        "view; crossings, open ground, close obstacles)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    progress_flag(p)
    p.set_defaults(func=run, check=check)


def run(args) -> int:
    from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset

    height, width = args.size
    path = write_synthetic_dataset(args.out, args.n, args.labeled, height, width, seed=args.seed,
                                   progress=not args.no_progress, overwrite=args.overwrite,
                                   scenes=args.scenes)
    print(f"wrote {counted(args.n, 'frame')} ({args.labeled} labelled, {height}x{width}, "
          f"{args.scenes} scenes) to {path}")
    return 0
