"""What a speed target asks of the machine: for each row of the benchmarks' JSON files, the time
that meets "ours <= 0.8 x PyTorch" and the rate of arithmetic (XLA's FLOP count per second) our
call would need to finish in it, as a fraction of the matmul peak measured in the same run.

    python experiments/bench_bounds.py        # the committed experiments/results/bench_*.json
    python experiments/bench_bounds.py experiments/results/bench_unet.json --target 0.8

A call cannot sustain more than the peak of a plain N x N matmul over its whole length (it also
has normalisation, activation, softmax and optimizer work, which do no matmul arithmetic), so a
target that needs close to 100 % of the peak is out of reach on that machine whatever the code
does, while one that needs less than what the call's own matmuls reach is a matter of the code.
Reads the JSON that `bench_unet.py` and `bench_depth_anything.py` write (`--json`); runs
nothing, so it takes no time and gives the same figures for the same files.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
DEFAULT_FILES = ("bench_unet.json", "bench_unet_512x640.json", "bench_unet_512x640_b4.json",
                 "bench_depth_anything.json")


def _row(what: str, ours_ms: float, torch_ms: float, flops: float, peak: float, target: float) -> dict:
    target_ms = target * torch_ms
    ours_gflops, needed_gflops = flops / ours_ms / 1e6, flops / target_ms / 1e6
    return {"what": what, "ours_ms": ours_ms, "torch_ms": torch_ms, "ratio": ours_ms / torch_ms,
            "target_ms": target_ms, "gflop": flops / 1e9, "ours_gflops": ours_gflops,
            "needed_gflops": needed_gflops, "peak_gflops": peak,
            "ours_peak_pct": 100.0 * ours_gflops / peak, "needed_peak_pct": 100.0 * needed_gflops / peak}


def target_rows(summary: dict, target: float = 0.8) -> list[dict]:
    """One dict per benchmarked call with a PyTorch figure in `summary` (the JSON of
    `bench_unet.py` or `bench_depth_anything.py`): what, ours_ms, torch_ms, ratio, target_ms
    (target x torch_ms), gflop (XLA's count for one call), ours_gflops, needed_gflops (gflop
    over target_ms), peak_gflops (the run's XLA matmul peak), ours_peak_pct, needed_peak_pct.
    Raises ValueError for JSON of another shape."""
    try:
        peak = summary["matmul_peak"]["xla_gflops"]
        results = summary["results"]
    except (KeyError, TypeError):
        raise ValueError("not a bench_unet / bench_depth_anything JSON (no matmul_peak or results)") from None
    rows = []
    for r in results:
        if "fwd_flops" in r:  # bench_unet
            size = f"{r['size'][0]}x{r['size'][1]}"
            for key, name in (("fwd", "forward"), ("train", "train step")):
                if r.get(f"{key}_torch_ms") is not None:
                    rows.append(_row(f"MTSA-UNet {summary.get('preset', '')} {name}, {size}, batch {r['batch']}",
                                     r[f"{key}_ours_ms"], r[f"{key}_torch_ms"], r[f"{key}_flops"], peak, target))
        elif "ours_over_theirs" in r:  # bench_depth_anything
            size = f"{r['size'][0]}x{r['size'][1]}"
            flops = r["ours_gflops"] * 1e9 * r["ours_ms"] / 1e3
            name = "forward" if r["kind"] == "forward" else "train step"
            rows.append(_row(f"Depth Anything V2 {summary.get('encoder', '')} {name}, {size}, batch {r['batch']} "
                             f"vs {r['reference']}", r["ours_ms"], r["theirs_ms"], flops, peak, target))
        else:
            raise ValueError(f"unknown benchmark row: {sorted(r)}")
    return rows


def print_rows(rows: list[dict], target: float) -> None:
    print(f"target: ours <= {target} x PyTorch. GFLOP/s: XLA's FLOP count of our call over a time; "
          "% of the run's XLA float32 matmul peak")
    header = (f"{'call':<72} | {'ours ms':>8} | {'torch ms':>8} | {'ratio':>5} | {'target ms':>9} | "
              f"{'GFLOP/s now':>11} | {'needed':>6} | {'peak':>5} | {'% peak now':>10} | {'% needed':>8}")
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['what']:<72} | {r['ours_ms']:>8.0f} | {r['torch_ms']:>8.0f} | {r['ratio']:>5.2f} | "
              f"{r['target_ms']:>9.0f} | {r['ours_gflops']:>11.0f} | {r['needed_gflops']:>6.0f} | "
              f"{r['peak_gflops']:>5.0f} | {r['ours_peak_pct']:>10.0f} | {r['needed_peak_pct']:>8.0f}")


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="*", metavar="JSON",
                        help="benchmark JSON files (default: the committed ones in experiments/results)")
    parser.add_argument("--target", type=float, default=0.8, help="ours / PyTorch to meet (default 0.8)")
    args = parser.parse_args(argv)
    if args.target <= 0:
        parser.error(f"--target must be positive, got {args.target}")
    files = args.files or [os.path.join(RESULTS, name) for name in DEFAULT_FILES]
    rows = []
    for path in files:
        if not os.path.isfile(path):
            sys.exit(f"bench_bounds: {path}: no such file")
        try:
            with open(path) as f:
                rows += target_rows(json.load(f), args.target)
        except (json.JSONDecodeError, ValueError) as e:
            sys.exit(f"bench_bounds: {path}: {e}")
    if not rows:
        sys.exit("bench_bounds: no row with a PyTorch figure in " + ", ".join(files))
    print_rows(rows, args.target)
    return rows


if __name__ == "__main__":
    main()
