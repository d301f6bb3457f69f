"""What the trained pipeline does to test frames: raw -> H, S, V -> pseudo-RGB -> depth.

    python experiments/pipeline_figure.py            # small preset, seed 0, synthetic benchmark
    python experiments/pipeline_figure.py --set data.scenes=varied stage1.steps_i2=2500 \
        --depth-init pretrained                       # the committed tables' protocol

Uses the Stage II run of table 1's HSV row (trained by the table scripts and cached; trained
here if not) and draws, for one test frame per lighting condition: the raw 14-bit frame, the
H (semantics), S (radiation gradients) and V (texture) channels of MTSA-UNet, the pseudo-RGB
image, the predicted depth and the ground truth (LiDAR-like sparse depth; dense depth where the
dataset has it). Writes experiments/results/pipeline_examples.png.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from irdepth_experiments import runner
from irdepth_experiments.cache import DEFAULT_CACHE, EVAL_SPLIT


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--preset", default="small", choices=("tiny", "small", "paper"))
    ap.add_argument("--seed", type=int, default=0, help="training seed of the run (default 0)")
    ap.add_argument("--data", default=None, help="dataset directory (default: synthetic)")
    ap.add_argument("--cache", default=DEFAULT_CACHE, help="the table scripts' cache")
    ap.add_argument("--quick", action="store_true", help="tiny preset, 2 steps per phase")
    ap.add_argument("--set", dest="overrides", nargs="*", default=[], metavar="KEY=VALUE",
                    help="the table scripts' --set (config overrides of every run), e.g. the "
                         "protocol's data.scenes=varied stage1.steps_i2=2500")
    ap.add_argument("--depth-init", default="random", choices=("random", "pretrained"),
                    help="the table scripts' --depth-init: where the Stage II run's Depth "
                         "Anything V2 started (pretrained: the network of depth_network.py)")
    ap.add_argument("--out", default=os.path.join(runner.RESULTS, "pipeline_examples.png"))
    args = ap.parse_args(argv)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    from irdepth_jax.models.pipeline import run_pipeline
    from irdepth_jax.predict_outputs import colorize_depth
    from irdepth_jax.runs.variables import load_model

    ctx = runner.context(preset=args.preset, seeds=(args.seed,), quick=args.quick,
                         data=args.data, overrides=args.overrides, cache=args.cache)
    if args.depth_init == "pretrained":
        from irdepth_experiments.depth_network import QUICK_RECIPE, RECIPE, pretrained_depth

        pretrained_depth(ctx, QUICK_RECIPE if args.quick else RECIPE)
    cfg, _, model = load_model(ctx.workdir("stage2", (), args.seed))
    dataset, indices = ctx.eval_source.frames(EVAL_SPLIT)
    samples = {}
    for i in indices:  # the first test frame of each condition, at most four rows
        s = dataset[int(i)]
        samples.setdefault(s["condition"], s)
        if len(samples) == 4:
            break
    samples = list(samples.values())

    out = run_pipeline(model["unet"], model["depth"], np.stack([s["raw14"] for s in samples]),
                       cfg)
    hsv, rgb, depth = (np.asarray(out[k]) for k in ("hsv", "rgb", "depth"))

    titles = ("raw 14-bit (1-99 % stretch)", "H: semantics", "S: gradients", "V: texture",
              "pseudo-RGB", "predicted depth", "ground truth (LiDAR-like)")
    fig, axes = plt.subplots(len(samples), len(titles), figsize=(2.1 * len(titles),
                                                                 1.9 * len(samples) + 0.6),
                             squeeze=False, layout="constrained")
    max_depth = cfg.data.max_depth
    for row, s, h, x, d in zip(axes, samples, hsv, rgb, depth):
        lo, hi = np.percentile(s["raw14"], (1, 99))
        gt = colorize_depth(s["depth"], max_depth) * s["valid"][..., None]
        images = (s["raw14"], h[..., 0], h[..., 1], h[..., 2], x,
                  colorize_depth(d, max_depth), gt)
        styles = (dict(cmap="gray", vmin=lo, vmax=hi), dict(cmap="hsv", vmin=0, vmax=1),
                  dict(cmap="magma", vmin=0, vmax=1), dict(cmap="gray", vmin=0, vmax=1),
                  {}, {}, {})
        for ax, image, style in zip(row, images, styles):
            ax.imshow(image, interpolation="nearest", **style)
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_ylabel(s["condition"])
    for ax, title in zip(axes[0], titles):
        ax.set_title(title, fontsize=8)
    fig.colorbar(ScalarMappable(Normalize(0.0, max_depth), cmap="turbo_r"), ax=axes[:, -2:],
                 orientation="horizontal", fraction=0.04, label="depth (m); near = red")
    origin = "SYNTHETIC benchmark" if ctx.data_info["source"] == "synthetic" else ctx.data_path
    settings = " ".join(args.overrides) or "no --set"
    fig.suptitle(f"{origin}, test split; preset {args.preset}, {settings}, depth network "
                 f"{args.depth_init}, seed {args.seed}"
                 f"{' (QUICK: untrained plumbing)' if args.quick else ''}", fontsize=9)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
