"""The paper's claims checked against the committed experiment results.

    python experiments/claims.py            # writes experiments/results/claims.md

Reads every ``experiments/results/<table>/results.json`` (or ``--results DIR``) and lists each
comparison the paper makes (`runner.CLAIMS`) with the paired per-seed difference (ours minus
baseline, signed so that positive favours the paper's claim), how many seeds agree, and the
paper's own difference for orientation.
"""

from __future__ import annotations

import argparse
import os

from runner import RESULTS, check_claims, load_results


def claims_markdown(records: dict[str, dict]) -> str:
    """Markdown table of `check_claims(records)` with the data and seeds it rests on."""
    rows = check_claims(records)
    synthetic = all(r["synthetic"] for r in records.values())
    seeds = sorted({tuple(r["seeds"]) for r in records.values()})
    presets = sorted({r["preset"] for r in records.values()})
    lines = ["# The paper's claims on our results", "",
             f"**Data: {'SYNTHETIC benchmark' if synthetic else 'see each table'}**; preset(s) "
             f"{', '.join(presets)}; seeds {', '.join(map(str, seeds))}. Written by "
             "`python experiments/claims.py` from the `results.json` files beside this one.", "",
             "Difference = ours − baseline, signed so that > 0 agrees with the paper; mean ± std "
             "over the paired seeds. Verdict: *holds* (every seed agrees), *opposite* (no seed "
             "does), *mixed*.", "",
             "| claim | table | ours: difference | seeds agreeing | verdict | paper: difference |",
             "|---|---|---|---|---|---|"]
    for c in rows:
        lines.append(f"| {c['claim']} | {c['table']} | {c['diff_mean']:+.4f} ± {c['diff_std']:.4f}"
                     f" | {c['agree']}/{c['n']} | {c['verdict']} | {c['paper_diff']:+.4f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--results", default=RESULTS, help="folder of <table>/results.json "
                                                       "(default: experiments/results)")
    ap.add_argument("--out", default=None, help="output file (default: RESULTS/claims.md)")
    args = ap.parse_args(argv)
    records = load_results(args.results)
    if not records:
        raise SystemExit(f"--results {args.results}: no <table>/results.json found")
    out = args.out or os.path.join(args.results, "claims.md")
    with open(out, "w") as f:
        f.write(claims_markdown(records))
    print(f"wrote {out} ({len(records)} tables)")


if __name__ == "__main__":
    main()
