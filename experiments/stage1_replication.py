"""Gate 2's pre-registered replication: the depth tables' Stage I model at seeds they never used.

Gate 2 (`claims.stage1_gate`, threshold `GATE_STAGE1_MIOU`) passed post hoc: the Stage I models of
seeds 0-2 scored mean mIoU 0.597 with training's running-average BatchNorm statistics and
failed, and 0.612 with the exact statistics that were written after that failure. This script
checks that pass on new seeds, under a rule fixed before any of its runs was trained (committed
on 2026-12-07 together with this script):

* the models: the protocol's Stage I model, the one every depth row starts from (`--set
  data.scenes=varied stage1.steps_i2=2500`), trained exactly as for seeds 0-2 at seeds 3 and 4
  (`REPLICATION_SEEDS`), evaluated as the tables evaluate it (mIoU over the six classes on the
  1,500 held-out evaluation renders);
* the rule: the replication passes when the mean mIoU of those seeds is >= `GATE_STAGE1_MIOU`
  (0.6), the gate's own threshold; nothing else is looked at to decide it;
* what follows: `claims.py` makes gate 2 pass only when the tables' models *and* the replication
  pass. A failed replication fails gate 2, and every depth verdict becomes "undecidable".

    python experiments/stage1_replication.py --set data.scenes=varied stage1.steps_i2=2500

(about 25 minutes per seed on 2 cores; finished runs are reused from the cache, and with
`--commit-stage1` their records and evaluations go to experiments/pretrained, from where a clone's
run of the command takes them instead of training). Writes
`experiments/results/stage1_replication/stage1_replication.json` (`--out` names another folder):
each seed's run and mIoU, the mean, the rule and whether it passed, the command, the git commit
it was written at and the code each run was trained by.
"""

from __future__ import annotations

import json
import os
import shlex
import sys
import time
from collections.abc import Sequence

import numpy as np

from irdepth_experiments.cache import COMMITTED_RUNS, Context, cache_relative, code_versions, commit_run, git_commit
from irdepth_experiments.depth_network import GATE_STAGE1_MIOU
from irdepth_experiments.runner import RESULTS, Table, parse_args
from irdepth_jax.hostmem import keep_freed_memory

REPLICATION_SEEDS = (3, 4)
"""Fixed before the replication's runs were trained; the tables use seeds 0-2."""
REPLICATION_RECORD = os.path.join(RESULTS, "stage1_replication", "stage1_replication.json")
RULE = (f"mean mIoU over seeds {' and '.join(map(str, REPLICATION_SEEDS))} of the protocol's Stage I "
        f"model >= {GATE_STAGE1_MIOU} (fixed before those runs were trained)")

TABLE = Table(
    name="stage1_replication",
    title="Gate 2's pre-registered replication: the depth rows' Stage I model at new seeds",
    about=("The Stage I model every depth row starts from, trained and evaluated as for the "
           f"tables at seeds {', '.join(map(str, REPLICATION_SEEDS))}; passes when {RULE}."),
    arms=(), columns=("miou",), paper={})


def replication(miou_by_seed: dict[int, float]) -> dict:
    """The rule applied: {'seeds', 'miou' (per seed), 'mean', 'threshold', 'rule', 'passed'}.

    Args:
      miou_by_seed: seed -> the Stage I model's mIoU on the evaluation set; must hold exactly
        `REPLICATION_SEEDS` (another set of seeds is not the pre-registered check).
    """
    if sorted(miou_by_seed) != sorted(REPLICATION_SEEDS):
        raise ValueError(f"the pre-registered replication is seeds {REPLICATION_SEEDS}, "
                         f"not {sorted(miou_by_seed)}")
    mean = float(np.mean(list(miou_by_seed.values())))
    return {"seeds": list(REPLICATION_SEEDS),
            "miou": {str(s): round(miou_by_seed[s], 4) for s in REPLICATION_SEEDS},
            "mean": round(mean, 4), "threshold": GATE_STAGE1_MIOU, "rule": RULE,
            "passed": mean >= GATE_STAGE1_MIOU}


def depth_tables_overrides() -> list[str] | None:
    """The `--set` overrides of the committed depth tables (the tables whose records list the
    Stage I models their rows started from), or None when none is committed; SystemExit when
    they differ from each other."""
    found = {}
    for name in sorted(os.listdir(RESULTS)):
        path = os.path.join(RESULTS, name, "results.json")
        if os.path.isfile(path):
            with open(path) as f:
                record = json.load(f)
            if record.get("stage1_models"):
                found[name] = record["overrides"]
    if len({tuple(o) for o in found.values()}) > 1:
        raise SystemExit(f"the committed depth tables were made with different --set: {found}")
    return next(iter(found.values()), None)


def main(argv: Sequence[str] | None = None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--seeds" in argv:
        raise SystemExit(f"--seeds: the replication's seeds are fixed ({REPLICATION_SEEDS})")
    args = parse_args(TABLE, argv + ["--seeds", *map(str, REPLICATION_SEEDS)])
    if args.quick or args.data is not None:
        raise SystemExit("the replication runs the synthetic benchmark's protocol (no --quick, no --data)")
    protocol = depth_tables_overrides()
    if protocol is not None and list(args.overrides) != protocol:
        raise SystemExit(f"--set {' '.join(args.overrides) or '(none)'}: the depth tables' Stage I "
                         f"models were trained with --set {' '.join(protocol)}; the replication "
                         "must train the same model")
    keep_freed_memory()
    started = time.time()
    ctx = Context(args)
    runs, miou = {}, {}
    for seed in REPLICATION_SEEDS:
        record = ctx.result("stage1", (), seed)
        runs[str(seed)] = record["run"]
        miou[seed] = record["stage1"]["all"].get("miou")
        if miou[seed] is None:
            raise SystemExit(f"{record['run']}: its evaluation has no mIoU (no segmentation "
                             "labels in the evaluation set); the replication cannot be decided")
    trained_by = {seed: code_versions(os.path.join(ctx.cache, "runs", run)) for seed, run in runs.items()}
    result = {**replication(miou), "runs": runs, "trained_by": trained_by, "overrides": list(args.overrides),
              "command": " ".join(["python", "experiments/stage1_replication.py"]
                                  + [shlex.quote(a) for a in argv]),
              "git": git_commit(), "eval_data": ctx.eval_info["path"],
              "wall_s": round(time.time() - started, 1)}
    result = json.loads(cache_relative(json.dumps(result), ctx.cache))
    out = os.path.join(args.out, os.path.basename(REPLICATION_RECORD))  # REPLICATION_RECORD by default
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        json.dump(result, f, indent=1)
        f.write("\n")
    if args.commit_stage1:  # records and evaluations only: no Stage II row starts from these
        for seed, run in runs.items():
            made_by = (f"# Stage I model (MTSA-UNet), seed {seed}\n\nMade by `{result['command']}` "
                       f"(git {result['git']}, with --commit-stage1): gate 2's pre-registered "
                       "replication (experiments/stage1_replication.py); its records and evaluation, "
                       f"without weights. mIoU {result['miou'][seed]} on the evaluation set "
                       f"({result['eval_data']}).\n")
            ctx.log(f"[stage1_replication] committed {commit_run(ctx.cache, run, COMMITTED_RUNS, made_by)}")
    ctx.log(f"[stage1_replication] mIoU {result['miou']}, mean {result['mean']:.4f}: "
            f"{'passed' if result['passed'] else 'FAILED'} ({RULE}); wrote {out}")
    return result


if __name__ == "__main__":
    main()
