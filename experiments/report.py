"""A table's outputs: results.md (mean +- std over seeds, per-seed values, the paper's figures,
provenance), results.json, frames.npz (the per-frame metrics of every row and seed, which
`irdepth_experiments.claims` reduces to per-seed differences) and figure.png (bars = mean, error bars = std
over seeds, dots = seeds)."""

from __future__ import annotations

import json
import os
import platform
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from irdepth_experiments.runner import Table

COLUMN_NAMES = {"d1": "δ<1.25", "d2": "δ<1.25²", "d3": "δ<1.25³", "abs_rel": "AbsRel",
                "sq_rel": "SqRel", "rmse": "RMSE", "silog": "SiLog", "ssim": "SSIM",
                "psnr": "PSNR", "entropy": "Entropy", "miou": "mIoU",
                "sky_far": "sky far (share)", "skyline_abs_rel": "AbsRel ≤ 3 px from sky"}
HIGHER_IS_BETTER = {"d1", "d2", "d3", "ssim", "psnr", "entropy", "miou", "sky_far"}


def hardware() -> dict:
    """CPU model, cores, platform and library versions of this machine."""
    import jax

    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()][:1] + (
                [f"... {len(jax.devices())} devices"] if len(jax.devices()) > 1 else []),
            "backend": jax.default_backend()}


# --------------------------------------------------------------------------- summary
def summarise(values: list[float]) -> dict:
    """{'mean', 'std' (sample std, 0 for one seed), 'n'} of finite values (NaN if none)."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], np.float64)
    if v.size == 0:
        return {"mean": float("nan"), "std": float("nan"), "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "n": int(v.size)}


def _fmt(x: float, col: str) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x:.2f}" if col in ("psnr", "rmse") else f"{x:.3f}"


def _depth_network(record: dict) -> str:
    """Where Stage II's Depth Anything V2 started, with the pretraining gate's figures."""
    network = record.get("depth_network")
    if network is None:
        return "random initialisation (`--depth-init random`; no pretraining gate)"
    verdict = "passed" if network["passed"] else "FAILED"
    return (f"pretrained ({network['made_by']}); gate {verdict}: δ<1.25 {network['rgb_d1']:.3f} on "
            f"held-out visible images, blank {network['blank_d1']:.3f} ({network['rule']})")


def markdown(table: Table, record: dict) -> str:
    """The results.md text of a finished table."""
    cols = table.columns
    head = "| " + " | ".join(["row"] + [COLUMN_NAMES[c] + (" ↑" if c in HIGHER_IS_BETTER else " ↓")
                                        for c in cols]) + " |"
    rule = "|---" * (len(cols) + 1) + "|"
    data, ev = record["data"], record["eval_data"]
    origin = ("SYNTHETIC benchmark (rendered scenes, not the paper's dataset)"
              if data["source"] == "synthetic" else f"dataset {data['path']} ({data['format']})")
    protocol = record["protocol"]
    every = "every frame" if protocol["stride"] == 1 else f"every {protocol['stride']}th frame"
    evaluated = (f"a separate evaluation set of {ev['num_frames']} rendered frames (dataset seed "
                 f"{ev['seed']})" if ev["source"] == "synthetic" else f"its {record['split']} split")
    lines = [f"# {table.title}", "",
             f"**Data: {origin}.** Mean ± std over seeds {record['seeds']} "
             f"(preset `{record['preset']}`{', QUICK smoke test: not a result' if record['quick'] else ''}); "
             f"evaluated on {evaluated}, {protocol['name']} protocol ("
             f"{every}, "
             f"alignment {protocol['align'] or 'none'}). Paired "
             "differences with 95 % intervals: `python experiments/claims.py` (claims.md).", "",
             table.about, "", head, rule]
    for row in record["rows"]:
        cells = [f"{_fmt(row['summary'][c]['mean'], c)} ± {_fmt(row['summary'][c]['std'], c)}"
                 for c in cols]
        lines.append(f"| {row['label']} | " + " | ".join(cells) + " |")
    lines += ["", "Per seed:", "", "| row | seed | " + " | ".join(COLUMN_NAMES[c] for c in cols) + " |",
              "|---" * (len(cols) + 2) + "|"]
    for row in record["rows"]:
        for seed, values in row["per_seed"].items():
            lines.append(f"| {row['label']} | {seed} | "
                         + " | ".join(_fmt(values.get(c), c) for c in cols) + " |")
    if table.paper:
        lines += ["", f"{table.paper_note}:", "",
                  "| row | " + " | ".join(COLUMN_NAMES[c] for c in cols) + " |",
                  "|---" * (len(cols) + 1) + "|"]
        for label, values in table.paper.items():
            lines.append(f"| {label} | " + " | ".join(_fmt(values.get(c), c) for c in cols) + " |")
    hw = record["hardware"]
    lines += ["", "Provenance:", "",
              f"- command: `{record['command']}`",
              f"- preset: `{record['preset']}`; overrides: "
              f"{', '.join(f'`{o}`' for o in record['overrides']) or 'none'}",
              f"- seeds: {record['seeds']}",
              f"- training data: {data.get('made_by', data['path'])} ({data['source']}, "
              f"{data['format']})",
              f"- evaluation data: {ev.get('made_by', ev['path'])} ({ev['source']}, {ev['format']})",
              f"- depth network: {_depth_network(record)}",
              f"- hardware: {hw['cpu']}, {hw['cores']} cores, {hw['backend']}; jax {hw['jax']}, "
              f"python {hw['python']}; {hw['platform']}",
              f"- code: git {record['git']}; wall time of this invocation "
              f"{record['wall_s']:.0f} s (cached runs count 0); training + evaluation time of "
              f"the runs read here, as measured when each ran: {record['runs_wall_s']:.0f} s",
              _runs_code(record),
              "- per-frame metrics of every row and seed: frames.npz beside this file",
              ""]
    return "\n".join(lines)


def _runs_code(record: dict) -> str:
    """The provenance line on the package code that trained the runs a table reads (each run's
    `cache.CODE_FILE` record, per seed in results.json as 'code'), counted by code digest: the
    same code under several commits is one version, one commit with different uncommitted
    changes two."""
    runs = {v["run"]: v.get("code") for row in record["rows"] for v in row["per_seed"].values()}
    commits: dict[str, list[str]] = {}
    counts: dict[str, int] = {}
    mixed = []
    for run, versions in runs.items():
        if versions is not None and len(versions) > 1:
            mixed.append(f"{run} ({', then '.join(_code_version(v) for v in versions)})")
            continue
        if not versions:
            key = "not recorded (trained before runs kept it)"
        else:
            key = f"code {versions[0]['digest']}"
            commits.setdefault(key, [])
            if versions[0]["git"] not in commits[key]:
                commits[key].append(versions[0]["git"])
        counts[key] = counts.get(key, 0) + 1
    parts = [f"{key}{' (git ' + ', '.join(commits[key]) + ')' if key in commits else ''}: "
             f"{n} run{'s' * (n > 1)}" for key, n in counts.items()]
    if mixed:
        parts.append("**resumed after the package changed, so neither version's (a fresh run of "
                     f"the command may differ): {', '.join(mixed)}**")
    return "- package code that trained the runs read here: " + "; ".join(parts)


def _code_version(version: dict) -> str:
    """'code <digest> (git <commit>)' of one `cache.CODE_FILE` entry."""
    return f"code {version['digest']} (git {version['git']})"


def figure(table: Table, record: dict, path: str) -> None:
    """Bar chart per metric: bars = rows (grouped by condition when rows have groups), error
    bars = std over seeds, dots = individual seeds."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = record["rows"], table.columns
    ncols = min(len(cols), 3)
    nrows = -(-len(cols) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.4 * ncols + 0.6, 2.9 * nrows + 1.2),
                             squeeze=False)
    for ax in axes.flat[len(cols):]:
        ax.set_visible(False)
    colors = plt.get_cmap("tab10").colors
    groups = list(dict.fromkeys(r["group"] for r in rows))
    series = list(dict.fromkeys(r["series"] for r in rows))
    width = 0.8 / len(series)
    for ax, col in zip(axes.flat, cols):
        for r in rows:
            gi, si = groups.index(r["group"]), series.index(r["series"])
            x = gi + (si - (len(series) - 1) / 2) * width
            s = r["summary"][col]
            ax.bar(x, s["mean"], width * 0.9, yerr=s["std"], capsize=3, color=colors[si % 10],
                   label=r["series"] if gi == 0 else None, alpha=0.85)
            seeds = [v.get(col) for v in r["per_seed"].values()]
            ax.plot([x] * len(seeds), seeds, "k.", ms=3)
        ax.set_title(COLUMN_NAMES[col] + (" ↑" if col in HIGHER_IS_BETTER else " ↓"), fontsize=10)
        ax.set_xticks(range(len(groups)))
        ax.set_xticklabels(groups if len(groups) > 1 else [""], fontsize=8)
        ax.tick_params(axis="y", labelsize=8)
        finite = [v for r in rows for v in [r["summary"][col]["mean"]] if np.isfinite(v)]
        if col in ("d1", "d2", "d3", "ssim") and finite and min(finite) > 0.5:
            ax.set_ylim(min(finite) - 0.1, 1.0)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(series), 6), fontsize=8,
               frameon=False)
    synthetic = record["data"]["source"] == "synthetic"
    fig.suptitle(f"{table.title}\n{'SYNTHETIC benchmark' if synthetic else record['data']['path']}"
                 f", preset {record['preset']}, seeds {record['seeds']}"
                 f"{' (QUICK smoke test)' if record['quick'] else ''}", fontsize=10)
    fig.tight_layout(rect=(0, 0.06 if nrows > 1 else 0.1, 1, 0.93 if nrows > 1 else 0.88))
    fig.savefig(path, dpi=110)
    plt.close(fig)




def write_outputs(table, record: dict, frames: dict[str, np.ndarray], out: str) -> None:
    """Writes results.json, results.md, frames.npz and figure.png of `table` into `out`."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "results.json"), "w") as f:
        json.dump(record, f, indent=2)
    with open(os.path.join(out, "results.md"), "w") as f:
        f.write(markdown(table, record))
    np.savez_compressed(os.path.join(out, "frames.npz"), **frames)
    figure(table, record, os.path.join(out, "figure.png"))
