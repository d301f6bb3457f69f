"""The paper's claims checked against the experiment results, with paired intervals and power.

    python experiments/claims.py            # prints the claims, writes experiments/results/claims.md

Reads every ``experiments/results/<table>/results.json`` and its ``frames.npz`` (or
``--results DIR``). For each comparison the paper makes (`CLAIMS`):

* **our effect**: ours minus baseline, signed so that > 0 agrees with the paper
  (lower-is-better columns negated), the mean over the seeds both rows have of the per-seed
  difference of the table's metric (a mean over frames; mIoU: of the pooled confusion matrix);
* **95 % interval**: a paired two-way bootstrap over seeds and test frames (`bootstrap`): each
  replicate resamples the seeds and, independently, the evaluation frames with replacement,
  the same ones for both rows (they were evaluated on the same frames with the same Stage I /
  initialisation per seed), and recomputes the effect; percentile interval of 10,000 replicates;
* **detectable effect**: (z_0.975 + z_0.8) x the bootstrap standard error: the smallest true
  effect this protocol finds (interval excluding 0) with 80 % probability at this number of
  seeds and frames;
* **verdict**: *reproduced* (interval above 0), *opposite* (below 0), *not reproduced* (contains
  0 although an effect of the paper's size would have been detectable), *undecided at this
  budget* (contains 0 and the paper's effect is below the detectable one), or *no claim* where
  the paper's own difference is not in its favour.

The paper's effects are on its private dataset; ours on the synthetic benchmark (or --data):
effect sizes in the same units, on different data, so "undecided" and "not reproduced" compare
our resolution with the size of effect the paper reports, nothing more.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from collections.abc import Sequence

import numpy as np

from experiments.report import COLUMN_NAMES, HIGHER_IS_BETTER
from experiments.runner import RECON_COLUMNS, RESULTS

REPLICATES = 10_000
Z_DETECT = 1.959964 + 0.841621  # two-sided 5 % test, 80 % power


@dataclasses.dataclass(frozen=True)
class Claim:
    """A comparison the paper makes: row `ours` beats row `baseline` on `column`.

    Rows are named by (series label, group) of a table's results.json; `paper` names the two
    rows of the table's `paper` dict."""

    table: str
    text: str
    ours: tuple[str, str]
    baseline: tuple[str, str]
    column: str
    paper: tuple[str, str]


def _claims() -> tuple[Claim, ...]:
    t1 = [Claim("table1_preprocessing", f"HSV beats {b} ({COLUMN_NAMES[c]})", ("HSV (ours)", "all"),
                (row, "all"), c, ("HSV (ours)", paper_row))
          for b, row, paper_row in (("HE", "HE", "HE"), ("CLAHE", "CLAHE", "CLAHE"),
                                    ("the camera chain", "camera-like (IRCBA stand-in)",
                                     "IRCBA (camera)"))
          for c in ("d1", "abs_rel")]
    t2 = [Claim("table2_multitask_reconstruction", f"multi-task beats single-task ({COLUMN_NAMES[c]})",
                ("multi-task (I-1 + I-2)", "all"), ("single-task (I-1 only)", "all"), c,
                ("multi-task", "single-task")) for c in RECON_COLUMNS]
    t3 = [Claim("table3_multitask_segmentation", "multi-task beats single-task (mIoU)",
                ("multi-task", "all"), ("single-task", "all"), "miou", ("multi-task", "single-task"))]
    t4 = [Claim("table4_illumination", f"IR beats RGB at {cond} ({COLUMN_NAMES[c]})",
                ("IR (HSV)", cond), ("RGB", cond), c, (f"IR ({cond})", f"RGB ({cond})"))
          for cond in ("day", "dusk", "night") for c in ("d1", "rmse")]
    t5 = [Claim("table5_rgg_reconstruction", f"RGG helps reconstruction ({COLUMN_NAMES[c]})",
                ("with RGG", "all"), ("without RGG", "all"), c, ("with RGG", "without RGG"))
          for c in RECON_COLUMNS]
    t6 = [Claim("table6_rgg_segmentation", "RGG helps segmentation (mIoU)", ("with RGG", "all"),
                ("without RGG", "all"), "miou", ("with RGG", "without RGG"))]
    t7 = [Claim("table7_sky_loss", f"the sky loss helps depth ({COLUMN_NAMES[c]})",
                ("with sky loss", "all"), ("without sky loss", "all"), c,
                ("with sky loss", "without sky loss")) for c in ("d1", "abs_rel")]
    return tuple(t1 + t2 + t3 + t4 + t5 + t6 + t7)


CLAIMS = _claims()
"""The paper's comparisons, checked by `check_claims` (notebooks/ablations.ipynb, README)."""


# --------------------------------------------------------------------------- statistics
def _metric(values: np.ndarray, weights: np.ndarray, column: str) -> np.ndarray:
    """The metric of frame weights (R, F) over per-frame values (F,) or confusion matrices
    (F, C, C): (R,) weighted means (mIoU of the weighted pooled matrix)."""
    if column == "miou":
        import jax

        from irdepth_jax.metrics import mean_iou

        pooled = np.einsum("rf,fij->rij", weights, values.astype(np.float64))
        return np.asarray(jax.jit(jax.vmap(mean_iou))(pooled.astype(np.float32)), np.float64)
    return weights @ values / weights.sum(-1)


def bootstrap(ours: Sequence[np.ndarray], base: Sequence[np.ndarray], column: str,
              replicates: int = REPLICATES, seed: int = 0) -> dict:
    """Paired two-way bootstrap of (ours - base) over seeds and frames.

    Args:
      ours, base: per seed (S of them, the same seeds in the same order), the per-frame values
        (F,) of the two rows on the same F frames, or (F, C, C) confusion matrices for 'miou'.
        Frames that are NaN in any array are dropped from all (a frame with too few valid
        pixels).
      column: the metric; lower-is-better columns are negated (> 0 favours `ours`).
    Returns:
      {'effect': mean over seeds of the per-seed difference, 'low', 'high': 95 % percentile
      interval, 'se': bootstrap standard error, 'detectable': Z_DETECT * se, 'seeds': S,
      'frames': F}.
    """
    ours, base = [np.asarray(a) for a in ours], [np.asarray(a) for a in base]
    if not ours or len(ours) != len(base):
        raise ValueError(f"bootstrap: {len(ours)} and {len(base)} seeds")
    if column != "miou":
        keep = np.all([np.isfinite(a) for a in ours + base], axis=0)
        ours, base = [a[keep] for a in ours], [b[keep] for b in base]
    seeds, frames = len(ours), len(ours[0])
    sign = 1.0 if column in HIGHER_IS_BETTER else -1.0
    rng = np.random.default_rng(seed)
    frame_w = np.stack([np.bincount(rng.integers(frames, size=frames), minlength=frames)
                        for _ in range(replicates)]).astype(np.float64)
    seed_w = np.stack([np.bincount(rng.integers(seeds, size=seeds), minlength=seeds)
                       for _ in range(replicates)]).astype(np.float64)
    full = np.ones((1, frames))
    per_seed = np.stack([sign * (_metric(o, frame_w, column) - _metric(b, frame_w, column))
                         for o, b in zip(ours, base)], axis=1)  # (R, S)
    point = np.mean([sign * (_metric(o, full, column) - _metric(b, full, column))[0]
                     for o, b in zip(ours, base)])
    replicate = (seed_w * per_seed).sum(-1) / seeds
    low, high = np.percentile(replicate, [2.5, 97.5])
    se = float(replicate.std(ddof=1))
    return {"effect": float(point), "low": float(low), "high": float(high), "se": se,
            "detectable": Z_DETECT * se, "seeds": seeds, "frames": frames}


def verdict(stats: dict, paper_effect: float) -> str:
    """The verdict of one claim (see the module docstring)."""
    if not paper_effect > 0:
        return "no claim (paper's difference ≤ 0)"
    if stats["low"] > 0:
        return "reproduced"
    if stats["high"] < 0:
        return "opposite"
    if paper_effect < stats["detectable"]:
        return "undecided at this budget"
    return "not reproduced"


# --------------------------------------------------------------------------- results
def load_results(results_dir: str) -> dict[str, dict]:
    """{table name: results.json record} of every ``<results_dir>/<name>/results.json``; each
    record gets 'frames_path' (its frames.npz, when present)."""
    out = {}
    for name in sorted(os.listdir(results_dir)):
        path = os.path.join(results_dir, name, "results.json")
        if os.path.isfile(path):
            with open(path) as f:
                out[name] = json.load(f)
            frames = os.path.join(results_dir, name, "frames.npz")
            out[name]["frames_path"] = frames if os.path.isfile(frames) else None
    return out


def check_claims(records: dict[str, dict], claims: Sequence[Claim] = CLAIMS,
                 replicates: int = REPLICATES) -> list[dict]:
    """Each claim of a loaded table: claim, table, column, paper_effect, seeds, the
    `bootstrap` statistics (effect, low, high, se, detectable, frames), agree (seeds whose own
    difference favours the paper) and verdict. A table without frames.npz is refused."""
    out = []
    for c in claims:
        record = records.get(c.table)
        if record is None:
            continue
        if not record.get("frames_path"):
            raise SystemExit(f"{c.table}: no frames.npz beside results.json (written by the "
                             "table script since the per-frame bootstrap); re-run the table")
        index = {(r["series"], r["group"]): i for i, r in enumerate(record["rows"])}
        i, j = index[c.ours], index[c.baseline]
        seeds = [s for s in record["rows"][i]["per_seed"] if s in record["rows"][j]["per_seed"]]
        key = "seg_cm" if c.column == "miou" else c.column
        with np.load(record["frames_path"]) as f:
            ours = [f[f"{i}:{s}:{key}"] for s in seeds]
            base = [f[f"{j}:{s}:{key}"] for s in seeds]
        stats = bootstrap(ours, base, c.column, replicates)
        sign = 1.0 if c.column in HIGHER_IS_BETTER else -1.0
        rows = record["rows"]
        agree = sum(sign * (rows[i]["per_seed"][s][c.column] - rows[j]["per_seed"][s][c.column]) > 0
                    for s in seeds)
        paper = record["paper"]
        paper_effect = sign * (paper[c.paper[0]][c.column] - paper[c.paper[1]][c.column])
        out.append({"claim": c.text, "table": c.table, "column": c.column, **stats,
                    "agree": int(agree), "paper_effect": paper_effect,
                    "verdict": verdict(stats, paper_effect)})
    return out


def claims_markdown(records: dict[str, dict], rows: list[dict]) -> str:
    """Markdown table of `check_claims` rows with the data and seeds they rest on."""
    synthetic = all(r["synthetic"] for r in records.values())
    seeds = sorted({tuple(r["seeds"]) for r in records.values()})
    presets = sorted({r["preset"] for r in records.values()})
    frames = sorted({r["eval_data"].get("num_frames", "?") for r in records.values()}, key=str)
    lines = ["# The paper's claims on our results", "",
             f"**Data: {'SYNTHETIC benchmark' if synthetic else 'see each table'}** (not the "
             f"paper's dataset); preset(s) {', '.join(presets)}; seeds "
             f"{', '.join(map(str, seeds))}; evaluation frames {', '.join(map(str, frames))}. "
             "Written by `python experiments/claims.py` from the `results.json` / `frames.npz` "
             "files beside this one; how each figure is computed: the docstring of "
             "experiments/claims.py.", "",
             "Effect = ours − baseline, signed so that > 0 agrees with the paper; 95 % interval "
             "of a paired bootstrap over seeds and test frames; *detectable* = the smallest "
             "effect found with 80 % power at this budget. The paper's effect is on its own "
             "data (orientation, not a target).", "",
             "| claim | table | paper effect | our effect [95 % interval] | detectable | "
             "seeds agreeing | verdict |",
             "|---|---|---|---|---|---|---|"]
    for c in rows:
        lines.append(f"| {c['claim']} | {c['table']} | {c['paper_effect']:+.4f} | "
                     f"{c['effect']:+.4f} [{c['low']:+.4f}, {c['high']:+.4f}] | "
                     f"{c['detectable']:.4f} | {c['agree']}/{c['seeds']} | {c['verdict']} |")
    counts = {}
    for c in rows:
        counts[c["verdict"]] = counts.get(c["verdict"], 0) + 1
    lines += ["", "Verdicts: " + ", ".join(f"{v}: {n}" for v, n in sorted(counts.items())) + "."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0],
                                 epilog="See the module docstring for the statistics.")
    ap.add_argument("--results", default=RESULTS, help="folder of <table>/results.json "
                                                       "(default: experiments/results)")
    ap.add_argument("--out", default=None, help="output file (default: RESULTS/claims.md)")
    ap.add_argument("--replicates", type=int, default=REPLICATES,
                    help=f"bootstrap replicates (default {REPLICATES})")
    args = ap.parse_args(argv)
    if not os.path.isdir(args.results):
        raise SystemExit(f"--results {args.results}: not a directory")
    records = load_results(args.results)
    if not records:
        raise SystemExit(f"--results {args.results}: no <table>/results.json found")
    rows = check_claims(records, replicates=args.replicates)
    text = claims_markdown(records, rows)
    out = args.out or os.path.join(args.results, "claims.md")
    with open(out, "w") as f:
        f.write(text)
    print(text, end="")
    print(f"wrote {out} ({len(records)} tables, {len(rows)} claims)")


if __name__ == "__main__":
    main()
