"""The depth network the depth tables start from, and the gates that say whether they can decide.

The paper fine-tunes a *pretrained* Depth Anything V2 (released weights, trained on visible
images) on its thermal inputs. We cannot download those weights, so we make the same situation:
``--depth-init pretrained`` pretrains our Depth Anything V2 on the visible images of a separate
rendered set (`irdepth train depth`, the recipe below) and starts every Stage II run from it.

Gates (`irdepth_experiments.claims` reports a depth claim as "undecidable: <gate>" when one fails):

1. pretraining: the pretrained network on the held-out evaluation renders' visible images
   reaches delta<1.25 >= `GATE_RGB_D1`, and >= `GATE_RGB_MARGIN` above the same network trained
   for the same steps on a constant grey image (what the scene layout alone gives); that blank
   network must itself reach `GATE_BLANK_HEALTHY` x the layout bound (`layout_bound`: the best
   per-pixel constant depth), or it collapsed and the margin over it would mean nothing;
2. Stage I: the multi-task model's segmentation mIoU on the evaluation set >= `GATE_STAGE1_MIOU`
   (so the Hue channel and the sky mask carry information);
3. per depth table: the HSV arm beats the blank-image control by >= `GATE_HSV_MARGIN`
   delta<1.25.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Sequence

import numpy as np

from irdepth_experiments.cache import (
    COMMITTED_RUNS,
    DEFAULT_CACHE,
    EVAL_SPLIT,
    REPO,
    Context,
    cache_relative,
    commit_run,
)

GATE_RGB_D1 = 0.85
GATE_RGB_MARGIN = 0.15
GATE_STAGE1_MIOU = 0.6
GATE_HSV_MARGIN = 0.10
GATE_BLANK_HEALTHY = 0.8
LAYOUT_TRAIN_FRAMES = 400  # training frames the layout bound is fitted on (every k-th)
GATE_RECORD = os.path.join(REPO, "experiments", "results", "depth_network.json")
"""Gate 1 as measured by ``--commit`` on the committed networks (`claims.json` shows it)."""
PILOT_RECORD = os.path.join(REPO, "experiments", "results", "depth_pilot.json")
"""The pilot (`pilot`, gates 2 and 3 at seed 0) as measured by ``--pilot --commit``."""


@dataclasses.dataclass(frozen=True)
class Recipe:
    """How the depth network is pretrained (`irdepth train depth` on rendered visible images).

    Attributes:
      frames: rendered frames of the pretraining set (all training frames; evaluation uses the
        benchmark's own held-out evaluation set).
      steps: optimizer steps (batch `stage2.batch_size` of the preset).
      learning_rate: backbone rate (the head's is `stage2.head_lr_multiplier` x it), poly decay.
      seed: training seed (one pretrained network for every Stage II seed, as one release).
      restarts: the later phases, each (steps, learning rate, frames): it fine-tunes the
        previous phase's network (`depth.checkpoint`) with a fresh optimizer and poly decay
        from its rate, a warm restart, on a pretraining set of `frames` rendered frames. The
        first 10,000 steps reached δ<1.25 0.825 on the held-out renders, still rising, and the
        first restart 0.847, with the gap between the training batches and the held-out
        renders grown from 0.007 to 0.028 (24 passes over the 6,000 frames): the third phase
        trains on twice the frames and reached 0.864. Each restart continues the network
        without retraining the phases before it.
      blank_overrides: what the blank network's recipe changes. Its head learns at the
        backbone's rate: at the usual 10x, the ReLU units of its head died within 50 steps in
        the pilot (a constant image gives every pixel the same features; gradient norm 0,
        δ<1.25 0.02), and a collapsed control says nothing of what the layout gives.
    """

    frames: int = 6000
    steps: int = 10000
    learning_rate: float = 1e-4
    seed: int = 0
    blank_overrides: tuple[str, ...] = ("stage2.head_lr_multiplier=1",)
    restarts: tuple[tuple[int, float, int], ...] = ((8000, 5e-5, 6000), (8000, 5e-5, 12000))

    def phase_frames(self) -> tuple[int, ...]:
        """The frames of each phase's pretraining set, first phase to last."""
        return (self.frames, *(frames for _, _, frames in self.restarts))

    def overrides(self, image: str) -> tuple[str, ...]:
        """The first phase's `train depth` overrides for the network trained on `image` ('rgb'
        or 'blank')."""
        return (f"stage2.preprocessing={image}", f"stage2.steps={self.steps}",
                f"stage2.learning_rate={self.learning_rate:g}",
                *(self.blank_overrides if image == "blank" else ()))

    def restart_overrides(self, image: str, restart: int, previous_phase: str) -> tuple[str, ...]:
        """The overrides of restart number `restart` (0: the second phase): it fine-tunes the
        run directory `previous_phase`."""
        steps, learning_rate, _ = self.restarts[restart]
        return (f"stage2.preprocessing={image}", f"stage2.steps={steps}",
                f"stage2.learning_rate={learning_rate:g}", f"depth.checkpoint={previous_phase}",
                *(self.blank_overrides if image == "blank" else ()))


RECIPE = Recipe()
QUICK_RECIPE = Recipe(frames=24, steps=2, restarts=((1, 5e-5, 24),))
"""--quick's: a smoke test of the mechanics, not a pretrained network."""


def layout_bound(train_depth: np.ndarray, eval_depth: np.ndarray,
                 candidates: np.ndarray = np.geomspace(0.5, 200.0, 120)) -> float:
    """δ<1.25 on `eval_depth` of the best image-blind prediction fitted on `train_depth`: per
    pixel, the candidate depth within 1.25x of the most training frames' valid depths there
    (what a network that ignores its input can at best learn for δ<1.25).

    Args:
      train_depth, eval_depth: (N, H, W) and (M, H, W) depth in metres, 0 where not valid.
      candidates: (K,) depths to choose from.
    Returns:
      the mean over evaluation frames of the share of valid pixels within 1.25x.
    """
    counts = np.stack([((train_depth > 0) & (np.maximum(c / np.maximum(train_depth, 1e-6),
                                                        train_depth / c) < 1.25)).sum(0)
                       for c in candidates])
    blind = candidates[counts.argmax(0)]  # (H, W)
    scores = [np.mean(np.maximum(blind[d > 0] / d[d > 0], d[d > 0] / blind[d > 0]) < 1.25)
              for d in eval_depth if (d > 0).any()]
    return float(np.mean(scores))


def gate_passed(rgb_d1: float, blank_d1: float, layout_d1: float) -> bool:
    """Gate 1 (module docstring) from the two networks' δ<1.25 and the layout bound's."""
    return bool(rgb_d1 >= GATE_RGB_D1 and rgb_d1 - blank_d1 >= GATE_RGB_MARGIN
                and blank_d1 >= GATE_BLANK_HEALTHY * layout_d1)


def _depths(dataset, indices) -> np.ndarray:
    return np.stack([dataset[int(i)]["depth"] for i in indices])


def network_phases(ctx: Context, image: str, recipe: Recipe = RECIPE) -> list[dict]:
    """The evaluation records of the recipe's phases for the network trained on `image` ('rgb'
    or 'blank'), first to last (each trained and evaluated first when not cached; the last is
    the network)."""
    first, *later = recipe.phase_frames()
    ctx.use_pretraining_set(first)
    records = [ctx.result("depth", recipe.overrides(image), recipe.seed)]
    for restart, frames in enumerate(later):
        previous = os.path.join(ctx.cache, "runs", records[-1]["run"])
        ctx.use_pretraining_set(frames)
        records.append(ctx.result("depth", recipe.restart_overrides(image, restart, previous), recipe.seed))
    ctx.use_pretraining_set(recipe.frames)
    return records


def pretrained_depth(ctx: Context, recipe: Recipe = RECIPE) -> str:
    """The run directory of the depth network pretrained on visible images (trained and
    evaluated first when not cached); sets it as every Stage II run's ``depth.checkpoint``."""
    workdir = os.path.join(ctx.cache, "runs", network_phases(ctx, "rgb", recipe)[-1]["run"])
    ctx.stage2_depth_checkpoint = workdir
    return workdir


def _pretraining_sets(ctx: Context, recipe: Recipe) -> list[str]:
    """How each phase's pretraining set is rendered, first phase to last (rendering it when
    absent); leaves `ctx` on the recipe's first set."""
    made_by = [ctx.use_pretraining_set(frames)["made_by"] for frames in recipe.phase_frames()]
    ctx.use_pretraining_set(recipe.frames)
    return made_by


def _made_by(info: dict, recipe: Recipe) -> str:
    """How the two networks are made, in words (`info`: the pretraining set's record)."""
    return (f"irdepth train depth on {recipe.frames} rendered visible frames "
            f"({info['height']}x{info['width']}, scenes {info['scenes']}, dataset seed "
            f"{info['seed']}), {recipe.steps} steps, backbone rate {recipe.learning_rate:g}"
            + "".join(f", then {steps} steps from it at {rate:g} (fresh optimizer, poly decay)"
                      + (f" on {frames} frames" if frames != recipe.frames else "")
                      for steps, rate, frames in recipe.restarts)
            + f", seed {recipe.seed}; blank: the same on a constant grey image"
            + (f" with {', '.join(recipe.blank_overrides)}" if recipe.blank_overrides else ""))


def pretraining_gate(ctx: Context, recipe: Recipe = RECIPE) -> dict:
    """Gate 1, measured: {'rgb_d1', 'blank_d1', 'passed', 'rule', 'made_by', ...} (the
    `depth_network` record of results.json and claims.json). Trains the two networks when not
    cached."""
    info = ctx.use_pretraining_set(recipe.frames)
    phases = {image: network_phases(ctx, image, recipe) for image in ("rgb", "blank")}
    d1 = {image: records[-1]["stage2"]["all"]["d1"] for image, records in phases.items()}
    train, train_idx = ctx.pretraining_source(recipe.frames)[0].frames("train")
    step = max(1, len(train_idx) // LAYOUT_TRAIN_FRAMES)
    bound = layout_bound(_depths(train, train_idx[::step]), _depths(*ctx.eval_source.frames(EVAL_SPLIT)))
    return {
        "rgb_d1": round(d1["rgb"], 4), "blank_d1": round(d1["blank"], 4),
        "phase_d1": {image: [round(r["stage2"]["all"]["d1"], 4) for r in records]
                     for image, records in phases.items()},
        "passed": gate_passed(d1["rgb"], d1["blank"], bound),
        "layout_bound_d1": round(bound, 4),
        "rule": f"rgb_d1 >= {GATE_RGB_D1} and rgb_d1 - blank_d1 >= {GATE_RGB_MARGIN} (delta<1.25 "
                "on the held-out evaluation renders' visible images), and blank_d1 >= "
                f"{GATE_BLANK_HEALTHY} x layout_bound_d1 (a blank network that collapsed is no "
                "control)",
        "made_by": _made_by(info, recipe),
        "encoder": ctx.base.depth.encoder, "recipe": dataclasses.asdict(recipe),
        "pretraining_data": _pretraining_sets(ctx, recipe),
    }


HSV_ROW = "HSV (ours)"
PILOT_ARMS = {HSV_ROW: ("stage2.preprocessing=hsv",),
              "camera-like": ("stage2.preprocessing=camera",),
              "blank (control)": ("stage2.preprocessing=blank",)}
"""The pilot's Stage II rows (table 1's), each started from the pretrained network."""


def pilot(ctx: Context, seed: int = 0, recipe: Recipe = RECIPE) -> dict:
    """The pilot of the depth tables: seed `seed` of `PILOT_ARMS`, each from the pretrained
    network (trained first when not cached), on the seed's Stage I model as the tables have
    it. Returns {row: {'d1', 'train_wall_s', 'eval_wall_s', 'run'}, 'stage1': that Stage I
    model's {'miou', 'run', 'train_wall_s'}, 'margin_over_blank': {row: δ<1.25 - the blank
    row's}, 'gates': {'stage1': mIoU >= `GATE_STAGE1_MIOU`, 'hsv_over_blank': the HSV row's
    margin >= `GATE_HSV_MARGIN`}}."""
    pretrained_depth(ctx, recipe)
    rows = {}
    for label, overrides in PILOT_ARMS.items():
        record = ctx.result("stage2", overrides, seed)
        rows[label] = {"d1": round(record["stage2"]["all"]["d1"], 4), "run": record["run"],
                       "train_wall_s": record["train_wall_s"], "eval_wall_s": record["eval_wall_s"]}
    stage1 = ctx.result("stage1", (), seed)  # the model the rows above read (cached)
    miou = round(stage1["stage1"]["all"]["miou"], 4)
    blank = rows["blank (control)"]["d1"]
    margins = {label: round(row["d1"] - blank, 4) for label, row in rows.items() if label != "blank (control)"}
    return {**rows, "stage1": {"miou": miou, "run": stage1["run"], "train_wall_s": stage1["train_wall_s"]},
            "margin_over_blank": margins,
            "gates": {"stage1": miou >= GATE_STAGE1_MIOU, "hsv_over_blank": margins[HSV_ROW] >= GATE_HSV_MARGIN}}


def commit_networks(ctx: Context, recipe: Recipe = RECIPE, into: str = COMMITTED_RUNS,
                    command: str = "", images: Sequence[str] = ("rgb", "blank")) -> list[str]:
    """Copies the networks trained on `images` ('rgb': the pretrained network, 'blank': its
    control), every phase of each, trained and evaluated in `ctx`'s cache (trained first when
    not), into `into` under their cache names (see `irdepth_experiments.cache.COMMITTED_RUNS`),
    each with a MADE_BY.md naming `command`; returns the directories written."""
    sets = _pretraining_sets(ctx, recipe)
    info = ctx.use_pretraining_set(recipe.frames)
    written = []
    for image in images:
        phases = network_phases(ctx, image, recipe)
        for number, record in enumerate(phases, 1):
            last = image == "rgb" and number == len(phases)
            weights = ("its weights are in checkpoints/" if last else "records only (weights not committed)")
            made_by = (f"# Depth Anything V2 trained on rendered "
                       f"{'visible' if image == 'rgb' else 'blank'} images: phase {number} of "
                       f"{len(phases)}\n\nMade by `{command}` (`experiments/depth_network.py`): "
                       f"{_made_by(info, recipe)}; {weights}.\n\ndelta<1.25 on the held-out "
                       f"evaluation renders' visible images ({record['eval_data']}): "
                       f"{record['stage2']['all']['d1']:.4f}.\nRecipe: "
                       f"`{json.dumps(dataclasses.asdict(recipe))}`. Pretraining data of this phase: "
                       f"`{sets[number - 1]}`.\n")
            target = commit_run(ctx.cache, record["run"], into, made_by, "stage2" if last else None)
            written.append(target)
    return written


def main(argv: Sequence[str] | None = None) -> dict:
    """Trains (or reuses from the cache) the pretrained depth network and its blank control,
    prints gate 1, and with --commit copies both into experiments/pretrained."""
    from irdepth_experiments import runner

    ap = argparse.ArgumentParser(
        prog="python experiments/depth_network.py",
        description="Pretrain Depth Anything V2 on rendered visible images (and the same on a "
                    "blank image), measure the pretraining gate, and optionally commit both "
                    f"runs. Recipe: {RECIPE}. On 2 CPU cores its three phases took about 5 "
                    "hours for the pretrained network (the first two shared with other runs; "
                    "the third, alone, 0.35 s a step) and 1 hour for the blank one, plus "
                    "rendering the frames; interrupted runs resume from their last checkpoint.")
    ap.add_argument("--preset", default="small", choices=("tiny", "small", "paper"))
    ap.add_argument("--cache", default=DEFAULT_CACHE, help="experiment cache (as the table scripts')")
    ap.add_argument("--set", dest="overrides", nargs="*", default=["data.scenes=varied"],
                    metavar="KEY=VALUE", help="config overrides (default: data.scenes=varied, "
                                              "what the depth tables run with)")
    ap.add_argument("--commit", action="store_true",
                    help=f"copy both runs into {os.path.relpath(COMMITTED_RUNS, REPO)}")
    ap.add_argument("--images", nargs="+", choices=("rgb", "blank"), default=["rgb", "blank"],
                    help="which networks to train (and commit); the gate needs both")
    ap.add_argument("--pilot", action="store_true",
                    help="then seed 0 of table 1's HSV, camera-like and blank rows from the "
                         "pretrained network: their delta<1.25, gate 2 (the Stage I model's mIoU) "
                         "and gate 3 (the margins over blank); with --commit written to "
                         f"{os.path.relpath(PILOT_RECORD, REPO)}")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    ctx = runner.context(args.preset, overrides=args.overrides, cache=args.cache,
                         progress=not args.no_progress)
    for image in args.images:
        for number, record in enumerate(network_phases(ctx, image), 1):
            print(f"{image} phase {number}: delta<1.25 {record['stage2']['all']['d1']:.4f} on "
                  f"{record['eval_data']} (run {record['run']})")
    gate = pretraining_gate(ctx) if set(args.images) == {"rgb", "blank"} else None
    if gate is not None:
        print(json.dumps(gate, indent=2))
    else:
        print("gate 1 needs both networks (--images rgb blank)")
    piloted = pilot(ctx) if args.pilot else None
    if piloted is not None:
        print(json.dumps(piloted, indent=2))
    if args.commit:
        from irdepth_experiments.cache import git_commit
        from irdepth_experiments.report import hardware

        command = " ".join(["python experiments/depth_network.py", *(argv if argv is not None else sys.argv[1:])])
        made = {"command": command, "git": git_commit(), "hardware": hardware(), "date": time.strftime("%Y-%m-%d")}
        for path in commit_networks(ctx, command=command, images=args.images):
            print(f"wrote {os.path.relpath(path, REPO)}")
        for record, path in ((gate, GATE_RECORD), (piloted, PILOT_RECORD)):
            if record is not None:
                with open(path, "w") as f:
                    f.write(cache_relative(json.dumps({**record, **made}, indent=2), ctx.cache) + "\n")
                print(f"wrote {os.path.relpath(path, REPO)}")
    return gate


if __name__ == "__main__":
    main()
