"""experiments/claims.py: seed-level inference, its calibration by simulation, and the committed
claims.json against a recomputation from the committed per-frame results."""

import functools
import json
import math
import os

import numpy as np
import pytest
from scipy import stats

from irdepth_experiments import claims, seed_stats

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(REPO, "experiments", "results")


def test_per_seed_differences_signs_pairs_and_drops_nan_frames():
    """ours = base + 0.1 on every frame: a difference of 0.1 per seed; a lower-is-better column
    counts a decrease as agreement; a frame that is NaN in any array leaves every seed."""
    base = [np.linspace(0.2, 0.8, 50), np.linspace(0.3, 0.7, 50)]
    up, frames = claims.per_seed_differences([b + 0.1 for b in base], base, "d1")
    np.testing.assert_allclose(up, [0.1, 0.1])
    assert frames == 50
    down, _ = claims.per_seed_differences([b - 0.1 for b in base], base, "abs_rel")
    np.testing.assert_allclose(down, [0.1, 0.1])
    nan = [np.r_[b[:-1], np.nan] for b in base]
    ours = [np.r_[b[:-1] + 0.1, 99.0] for b in base]  # its last frame must not count
    diffs, frames = claims.per_seed_differences(ours, nan, "d1")
    assert frames == 49
    np.testing.assert_allclose(diffs, [0.1, 0.1])
    with pytest.raises(ValueError, match="2 and 1 seeds"):
        claims.per_seed_differences(base, base[:1], "d1")


def test_per_seed_differences_pool_confusion_matrices_for_miou():
    """mIoU of the pooled matrix, not a mean of per-frame IoUs: two classes, `ours` perfect,
    `base` confusing half of class 1 (IoU 10/15 and 5/10 -> mIoU 7/12)."""
    perfect = np.array([[10, 0], [0, 10]])
    half = np.array([[10, 0], [5, 5]])
    diffs, frames = claims.per_seed_differences([np.stack([perfect] * 20)], [np.stack([half] * 20)],
                                                "miou")
    assert frames == 20
    assert diffs[0] == pytest.approx(1 - 7 / 12, rel=1e-5)


def test_seed_level_is_the_paired_t_test_worked_by_hand():
    """d = 0.1, 0.2, 0.3: mean 0.2, sd 0.1, se 0.1/sqrt(3); t = 3.4641 on 2 df; t_0.975,2 =
    4.302653 -> interval 0.2 ± 0.248414, p = 0.07418 (scipy's one-sample t-test agrees)."""
    st = seed_stats.seed_level(np.array([0.1, 0.2, 0.3]))
    assert st["effect"] == pytest.approx(0.2)
    assert st["sd"] == pytest.approx(0.1)
    assert st["low"] == pytest.approx(0.2 - 0.248414, abs=1e-6)
    assert st["high"] == pytest.approx(0.2 + 0.248414, abs=1e-6)
    assert st["p"] == pytest.approx(0.07418, abs=1e-5)
    assert st["p"] == pytest.approx(stats.ttest_1samp([0.1, 0.2, 0.3], 0.0).pvalue)
    one = seed_stats.seed_level(np.array([0.3]))  # one seed: no interval
    assert math.isnan(one["p"]) and one["low"] == -math.inf and one["high"] == math.inf
    same = seed_stats.seed_level(np.array([0.25, 0.25, 0.25]))
    assert same["p"] == 0.0 and same["low"] == same["high"] == 0.25


def test_detectable_effect_has_80_percent_power():
    """At the detectable effect the t-test rejects in 80 % of simulated experiments; it lies
    above the normal-theory (t_0.975 + t_0.8) x se at few seeds and tends to 2.80 x se."""
    sd = 0.05
    for seeds in (3, 5, 10):
        detect = seed_stats.detectable_effect(sd, seeds)
        assert seed_stats.power(detect, sd, seeds) == pytest.approx(0.8, abs=1e-6)
        se = sd / math.sqrt(seeds)
        approx = (stats.t.ppf(0.975, seeds - 1) + stats.t.ppf(0.8, seeds - 1)) * se
        assert approx < detect < 1.15 * approx
    d = 0.05 * np.random.default_rng(0).standard_normal((4000, 3)) + seed_stats.detectable_effect(sd, 3)
    rejected = stats.ttest_1samp(d, 0.0, axis=1).pvalue < 0.05
    assert rejected.mean() == pytest.approx(0.8, abs=0.025)
    se = sd / math.sqrt(400)
    assert seed_stats.detectable_effect(sd, 400) == pytest.approx(2.8016 * se, rel=0.01)
    assert seed_stats.detectable_effect(sd, 1) == math.inf


def test_seeds_needed_is_the_first_budget_with_enough_power():
    for effect, sd in ((0.02, 0.05), (0.1, 0.05), (0.3, 0.05)):
        n = seed_stats.seeds_needed(effect, sd)
        assert seed_stats.power(effect, sd, n) >= 0.8
        assert n == 2 or seed_stats.power(effect, sd, n - 1) < 0.8
    assert seed_stats.seeds_needed(-0.1, 0.05) is None
    assert seed_stats.seeds_needed(1e-6, 1.0) is None  # more than MAX_SEEDS
    assert seed_stats.seeds_needed(0.1, 0.0) == 2


def test_holm_worked_by_hand():
    """p = 0.01, 0.04, 0.03 (m = 3): 0.01 x 3 = 0.03; 0.03 x 2 = 0.06; 0.04 x 1 -> max(0.06,
    0.04) = 0.06. NaN (untested) is left out of m."""
    np.testing.assert_allclose(seed_stats.holm([0.01, 0.04, 0.03, math.nan])[:3], [0.03, 0.06, 0.06])
    assert math.isnan(seed_stats.holm([0.01, math.nan])[1])
    assert seed_stats.holm([0.6, 0.7]) == [1.0, 1.0]


def test_verdicts():
    s = {"effect": 0.03, "low": 0.01, "high": 0.05, "p_holm": 0.01}
    assert claims.verdict(s, 0.03, 0.01) == "reproduced"
    assert claims.verdict({**s, "effect": -0.03, "low": -0.05, "high": -0.01}, 0.03, 0.01) == "opposite"
    inside = {"effect": 0.001, "low": -0.004, "high": 0.006, "p_holm": 0.6}
    assert claims.verdict(inside, 0.03, 0.01) == "no effect (equivalent)"
    assert claims.verdict({**inside, "high": 0.02}, 0.03, 0.01) == "undecided"
    assert claims.verdict(s, -0.002, 0.01) == "no claim"
    assert claims.margin_of("d1", 0.003) == 0.003 and claims.margin_of("d1", 0.5) == 0.01


def _depth_records(hsv_d1, blank_d1, network, miou):
    """Synthetic results.json records: table 1 (HSV, HE, blank: δ<1.25 per seed) with its
    frames.npz stand-in, and the mIoU of the Stage I models its rows started from (two seeds:
    `miou` - 0.01 and `miou` + 0.01)."""
    def row(series, d1):
        return {"series": series, "group": "all", "label": series,
                "per_seed": {str(s): {"d1": v, "abs_rel": 0.1} for s, v in enumerate(d1)}}
    t1 = {"rows": [row("HSV (ours)", hsv_d1), row("HE", [v - 0.05 for v in hsv_d1]),
                   row("CLAHE", hsv_d1), row("camera-like (IRCBA stand-in)", hsv_d1)]
          + ([row("blank (control)", blank_d1)] if blank_d1 else []),
          "depth_network": network,
          "stage1_models": [{"seed": 0, "run": "stage1-a", "miou": miou - 0.01},
                            {"seed": 1, "run": "stage1-b", "miou": miou + 0.01}]}
    return {"table1_preprocessing": t1}


@pytest.fixture
def no_replication(tmp_path, monkeypatch):
    """Gate 2 without a committed replication record (the synthetic records stand alone)."""
    monkeypatch.setattr(claims, "REPLICATION_RECORD", str(tmp_path / "none.json"))


def test_depth_claims_are_undecidable_unless_every_gate_passes(no_replication):
    """Gate by gate: a random-init depth network, a Stage I below the mIoU gate, a missing blank
    row, and a row less than 0.10 δ<1.25 above the blank row each make a table-1 claim
    'undecidable: <that gate>'; with all three passed there is no gate verdict."""
    network = {"passed": True, "rule": "r", "rgb_d1": 0.9, "blank_d1": 0.3}
    claim = claims.CLAIMS[0]
    assert claim.table == "table1_preprocessing" and claim.column == "d1"

    def gate(hsv_d1, blank_d1, network, miou):
        records = _depth_records(hsv_d1, blank_d1, network, miou)
        return claims._undecidable(claim, records[claim.table], claims.depth_gates(records))

    good = ([0.80, 0.82, 0.81], [0.60, 0.65, 0.70])  # margin 0.16
    assert gate(*good, network, 0.7) is None
    assert gate(*good, None, 0.7) == "undecidable: pretraining gate"
    assert gate(*good, {**network, "passed": False}, 0.7) == "undecidable: pretraining gate"
    assert gate(*good, network, 0.59) == "undecidable: Stage I gate"
    assert gate(good[0], None, network, 0.7) == "undecidable: blank-control gate"
    assert gate(good[0], [0.72, 0.72, 0.72], network, 0.7) == "undecidable: blank-control gate"
    assert gate(good[0], [0.70, 0.71, 0.72], network, 0.7) is None  # margin 0.10 exactly
    records = _depth_records(*good, network, 0.7)
    control = claims.blank_control_gate(claim, records[claim.table])
    assert control["margin_d1"] == pytest.approx(0.81 - 0.65)
    assert claims.depth_gates(records)["stage1"]["miou"] == pytest.approx(0.7)
    # a depth table that does not record its Stage I models' mIoU (made before the record)
    del records[claim.table]["stage1_models"]
    assert claims._undecidable(claim, records[claim.table], claims.depth_gates(records)) == \
        "undecidable: Stage I gate"
    # the lowest depth table decides: table 7's Stage I below the gate fails table 1's claims too
    records = _depth_records(*good, network, 0.7)
    records["table7_sky_loss"] = {"rows": [], "stage1_models": [{"seed": 0, "run": "s", "miou": 0.5}]}
    assert not claims.depth_gates(records)["stage1"]["passed"]
    # a claim outside the depth tables is never gated
    table2 = claims.Claim("table2_multitask_reconstruction", "", ("a", "all"), ("b", "all"), "ssim",
                          ("a", "b"))
    assert claims._undecidable(table2, {}, claims.depth_gates({})) is None


def test_gate_2_needs_its_pre_registered_replication_to_pass_once_it_is_measured(no_replication):
    """The replication's rule worked by hand (mean of seeds 3 and 4 >= 0.6), and gate 2 with it:
    not yet run -> the tables' models decide, said so; passed -> passes; failed -> gate 2
    fails and a depth claim is 'undecidable: Stage I gate' though the tables' models passed."""
    from irdepth_experiments.stage1_replication import replication

    passed, failed = replication({3: 0.62, 4: 0.59}), replication({3: 0.61, 4: 0.58})
    assert passed["mean"] == pytest.approx(0.605) and passed["passed"]
    assert failed["mean"] == pytest.approx(0.595) and not failed["passed"]
    with pytest.raises(ValueError, match="seeds"):
        replication({3: 0.7, 5: 0.7})  # not the pre-registered seeds
    network = {"passed": True, "rule": "r", "rgb_d1": 0.9, "blank_d1": 0.3}
    records = _depth_records([0.80, 0.82, 0.81], [0.60, 0.65, 0.70], network, 0.7)
    claim = claims.CLAIMS[0]
    alone = claims.stage1_gate(records)
    assert alone["passed"] and alone["replication"] is None and "not yet run" in alone["why"]
    assert claims.stage1_gate(records, passed)["passed"]
    gate = claims.stage1_gate(records, failed)
    assert not gate["passed"] and gate["miou"] == pytest.approx(0.7) and "FAILED" in gate["why"]
    with open(claims.REPLICATION_RECORD, "w") as f:
        json.dump(failed, f)
    assert claims._undecidable(claim, records[claim.table], claims.depth_gates(records)) == \
        "undecidable: Stage I gate"


def test_the_committed_pretrained_network_is_shown_and_whether_the_tables_used_it(tmp_path, monkeypatch):
    """claims.json's `depth_network.pretrained_network`: gate 1 as `depth_network.py --commit`
    recorded it, 'used_by_tables' only when the depth tables' network is that one; claims.md
    says it; absent before a network is committed."""
    record = {"rgb_d1": 0.86, "blank_d1": 0.31, "layout_bound_d1": 0.34, "phase_d1": {}, "passed": True,
              "rule": "r", "made_by": "m", "command": "c", "date": "2026-12-07", "git": "g"}
    path = tmp_path / "depth_network.json"
    monkeypatch.setattr(claims, "committed_network", functools.partial(claims.committed_network, str(path)))
    assert claims.depth_gates({})["pretrained_network"] is None
    path.write_text(json.dumps(record))
    unused = claims.depth_gates(_depth_records([0.8], [0.6], None, 0.7))["pretrained_network"]
    assert unused["rgb_d1"] == 0.86 and unused["passed"] and not unused["used_by_tables"]
    assert "git" not in unused
    used = claims.depth_gates(_depth_records([0.8], [0.6], dict(record), 0.7))["pretrained_network"]
    assert used["used_by_tables"]
    records = {k: {**v, "synthetic": True, "seeds": [0], "preset": "small", "eval_data": {}}
               for k, v in _depth_records([0.8], [0.6], None, 0.7).items()}
    md = claims.claims_markdown(records, [])
    assert "gate 1 passed, δ<1.25 0.860 on visible images, blank 0.310" in md
    assert "these tables did not start from it" in md


def _simulated_experiments(effect: float, sims: int, seeds: int = 3, frames: int = 200, seed: int = 0):
    """Per-frame results of two paired rows as our tables have them: a frame difficulty shared
    by every run, a per-seed offset shared by the seed's two rows, a per-seed deviation of the
    effect (seed-level variance: the unit) and per-frame noise. Yields (ours, base) per
    simulated experiment, lists of (frames,) arrays per seed."""
    rng = np.random.default_rng(seed)
    difficulty = rng.uniform(0.3, 0.8, frames)
    for _ in range(sims):
        offset = 0.03 * rng.standard_normal((seeds, 1))
        deviation = 0.03 * rng.standard_normal((seeds, 1))
        base = difficulty + offset + 0.1 * rng.standard_normal((seeds, frames))
        ours = difficulty + offset + effect + deviation + 0.1 * rng.standard_normal((seeds, frames))
        yield list(ours), list(base)


def test_the_interval_covers_the_true_effect_at_three_seeds():
    """95 % nominal: at 3 seeds it covers the true effect in >= 93 % of 2,000 simulations
    (Monte Carlo standard error 0.5 %), and is not needlessly wide (<= 97 %)."""
    covered = []
    for ours, base in _simulated_experiments(0.02, 2000):
        st = seed_stats.seed_level(claims.per_seed_differences(ours, base, "d1")[0])
        covered.append(st["low"] <= 0.02 <= st["high"])
    assert 0.93 <= np.mean(covered) <= 0.97


@pytest.mark.parametrize("family", [1, 3, 6])
def test_no_effect_rarely_gives_a_verdict_of_direction(family):
    """Zero effect: 'reproduced' or 'opposite' in <= 5 % of the claims, for a table of 1, 3 and 6
    claims (tables 3, 2 and 1) with Holm's adjustment across the table. A single claim is tested
    at exactly 5 % for normal per-seed differences, so its Monte Carlo rate may exceed 5 % by
    sampling error alone: 6,000 simulations, bound 5 % + 2.6 standard errors (0.7 %)."""
    sims = 6000 // family
    experiments = _simulated_experiments(0.0, sims * family, seed=family)
    directional = 0
    for _ in range(sims):
        rows = []
        for _claim in range(family):
            ours, base = next(experiments)
            rows.append(seed_stats.seed_level(claims.per_seed_differences(ours, base, "d1")[0]))
        for st, p_holm in zip(rows, seed_stats.holm([st["p"] for st in rows])):
            directional += claims.verdict({**st, "p_holm": p_holm}, 0.02, 0.01) in ("reproduced", "opposite")
    rate = directional / (sims * family)
    bound = 0.05 + (2.6 * math.sqrt(0.05 * 0.95 / 6000) if family == 1 else 0.0)
    assert rate <= bound


def _committed():
    path = os.path.join(RESULTS, "claims.json")
    if not os.path.isfile(path):
        pytest.skip("no committed experiments/results/claims.json")
    with open(path) as f:
        return json.load(f)


def test_committed_claims_are_what_the_committed_frames_give():
    """A reviewer's recomputation: claims.json is check_claims of the committed results.json /
    frames.npz, and claims.md says the same verdicts."""
    committed = _committed()
    records = claims.load_results(RESULTS)
    fresh = claims.claims_json(records, claims.check_claims(records))
    assert [c["verdict"] for c in committed["claims"]] == [c["verdict"] for c in fresh["claims"]]
    for old, new in zip(committed["claims"], fresh["claims"]):
        assert {k: old[k] for k in ("table", "row", "baseline", "metric")} == \
            {k: new[k] for k in ("table", "row", "baseline", "metric")}
        assert old["effect"] == pytest.approx(new["effect"], abs=1e-9)
        assert old["interval"] == pytest.approx(new["interval"], abs=1e-9)
    with open(os.path.join(RESULTS, "claims.md")) as f:
        md = f.read()
    for c in committed["claims"]:
        assert f"| {c['claim']} | {c['table']} |" in md
        assert md.count(f"| {c['verdict']} |") >= 1


def test_committed_verdicts_of_direction_hold_at_seed_level():
    """Every 'reproduced' / 'opposite' verdict: the per-seed differences of the committed
    frames.npz give a paired t-interval (df = seeds - 1) on that side of 0, and a Holm-adjusted p
    below 5 %."""
    for c in _committed()["claims"]:
        if c["verdict"] not in ("reproduced", "opposite"):
            continue
        records = claims.load_results(RESULTS)
        rows = {(r["label"]): i for i, r in enumerate(records[c["table"]]["rows"])}
        i, j = rows[c["row"]], rows[c["baseline"]]
        key = "seg_cm" if c["metric"] == "miou" else c["metric"]
        with np.load(records[c["table"]]["frames_path"]) as f:
            seeds = sorted({k.split(":")[1] for k in f.files if k.startswith(f"{i}:")})
            d, _ = claims.per_seed_differences([f[f"{i}:{s}:{key}"] for s in seeds],
                                               [f[f"{j}:{s}:{key}"] for s in seeds], c["metric"])
        low, high = stats.t.interval(0.95, len(d) - 1, loc=d.mean(), scale=d.std(ddof=1) / math.sqrt(len(d)))
        assert (low > 0) if c["verdict"] == "reproduced" else (high < 0), c["claim"]
        assert c["p_holm"] < 0.05


def test_committed_replication_is_what_its_committed_runs_scored():
    """A reviewer's recomputation of gate 2's replication: each seed's mIoU in the committed
    record is its committed run's evaluation, the mean and the verdict follow from the rule, the
    seeds are the pre-registered ones, and claims.json's gate carries the same record."""
    from irdepth_experiments.cache import COMMITTED_RUNS
    from irdepth_experiments.stage1_replication import REPLICATION_RECORD, REPLICATION_SEEDS, replication

    if not os.path.exists(REPLICATION_RECORD):
        pytest.skip("no committed replication record")
    with open(REPLICATION_RECORD) as f:
        record = json.load(f)
    scored = {}
    for seed in REPLICATION_SEEDS:
        run = os.path.join(COMMITTED_RUNS, record["runs"][str(seed)])
        (evaluation,) = [n for n in os.listdir(run) if n.startswith("eval-") and n.endswith(".json")]
        with open(os.path.join(run, evaluation)) as f:
            scored[seed] = json.load(f)["stage1"]["all"]["miou"]
    assert {k: record[k] for k in ("seeds", "miou", "mean", "threshold", "rule", "passed")} == \
        replication(scored)
    assert _committed()["depth_network"]["stage1"]["replication"] == record
