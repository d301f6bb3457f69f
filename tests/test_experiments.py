"""The ablation scripts (experiments/table*.py) in --quick mode, and the runner's bookkeeping.

All scripts run in this process against one session-wide cache (dataset, runs, XLA
compilation cache), so the Stage I model of the quick config is trained once and shared by the
tables, as it is for the real runs.

The default suite runs tables 2 and 3 (Stage I only: about 2.5 minutes on 2 cores); the other
five train Stage II arms (about 5 more minutes) and run with ``-m slow``, as do the tests that
need them.
"""

from __future__ import annotations

import dataclasses
import glob
import importlib
import json
import math
import os
import types

import jax
import numpy as np
import pytest

from irdepth_experiments import cache, claims, report, runner

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TABLES = ("table1_preprocessing", "table2_multitask_reconstruction",
          "table3_multitask_segmentation", "table4_illumination", "table5_rgg_reconstruction",
          "table6_rgg_segmentation", "table7_sky_loss")
DEFAULT_TABLES = ("table2_multitask_reconstruction", "table3_multitask_segmentation")
"""The tables the default suite runs; the others are `slow`."""
SLOW_TABLES = tuple(name for name in TABLES if name not in DEFAULT_TABLES)


def table_param(name: str):
    """`name` as a pytest parameter, marked slow unless it is one of `DEFAULT_TABLES`."""
    return name if name in DEFAULT_TABLES else pytest.param(name, marks=pytest.mark.slow)


def load_script(name: str):
    """The module irdepth_experiments.<name> (a table script)."""
    return importlib.import_module(f"irdepth_experiments.{name}")


def quick_cache_dir(tmp_path_factory) -> str:
    """The session's experiment cache (also used by tests/test_notebooks.py)."""
    return str(tmp_path_factory.getbasetemp() / "experiments_cache")


@pytest.fixture(scope="session")
def quick_cache(tmp_path_factory):
    """Dataset and runs in a fresh temporary cache (compiled steps go to the test run's XLA
    cache, see conftest.py)."""
    return quick_cache_dir(tmp_path_factory)


class QuickTables:
    """name -> (results.json record, output dir) of a table in --quick mode, each table run on
    first use into one output root (later tables reuse the runs of earlier ones)."""

    def __init__(self, cache: str, out_root):
        self.cache, self.out_root, self.done = cache, out_root, {}

    def __getitem__(self, name: str) -> tuple[dict, str]:
        if name not in self.done:
            out, script = str(self.out_root / name), load_script(name)
            script.main(script.TABLE, ["--quick", "--cache", self.cache, "--out", out,
                                       "--no-progress"])
            with open(os.path.join(out, "results.json")) as f:
                self.done[name] = (json.load(f), out)
        return self.done[name]


@pytest.fixture(scope="session")
def quick_results(quick_cache, tmp_path_factory):
    """`QuickTables` of the session (a table runs when a test first asks for it)."""
    return QuickTables(quick_cache, tmp_path_factory.mktemp("experiment_results"))


def finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


@pytest.mark.parametrize("name", [table_param(name) for name in TABLES])
def test_quick_outputs(quick_results, name):
    table = load_script(name).TABLE
    record, out = quick_results[name]
    for f in ("results.md", "results.json", "figure.png"):
        assert os.path.getsize(os.path.join(out, f)) > 0, f
    # provenance
    assert record["synthetic"] is True and record["quick"] is True
    assert record["preset"] == "tiny" and record["seeds"] == [0]
    assert record["command"].startswith(f"python experiments/{name}.py --quick")
    assert record["data"]["source"] == "synthetic"
    assert record["hardware"]["cores"] >= 1 and record["hardware"]["jax"] == jax.__version__
    assert "stage2.steps=2" in record["overrides"]
    # one row per arm, every declared column, finite numbers in range
    assert record["columns"] == list(table.columns)
    assert [r["series"] for r in record["rows"]] == [a.label for a in table.arms]
    assert record["eval_data"]["num_frames"] == runner.QUICK_EVAL_FRAMES
    assert record["protocol"] == {"name": "synthetic", "stride": 1, "align": None}
    with np.load(os.path.join(out, "frames.npz")) as f:  # per-frame values behind each mean
        for i, row in enumerate(record["rows"]):
            for col in table.columns:
                if col == "miou":
                    assert f[f"{i}:0:seg_cm"].ndim == 3
                    continue
                values = f[f"{i}:0:{col}"]
                assert len(values) == row["per_seed"]["0"]["count"]
                assert float(np.nanmean(values)) == pytest.approx(row["per_seed"]["0"][col], rel=1e-5)
    for row in record["rows"]:
        values = row["per_seed"]["0"]
        assert values["count"] > 0
        for col in table.columns:
            assert finite(values[col]), (row["label"], col, values[col])
            assert row["summary"][col]["mean"] == pytest.approx(values[col])
            assert row["summary"][col]["std"] == 0.0 and row["summary"][col]["n"] == 1
        if "d1" in values:
            assert 0.0 <= values["d1"] <= values["d2"] <= values["d3"] <= 1.0
            assert values["abs_rel"] >= 0 and values["rmse"] >= 0
        if "psnr" in values:
            assert -1.0 <= values["ssim"] <= 1.0 and values["psnr"] > 0
            assert 0.0 <= values["entropy"] <= 8.0
        if "miou" in values:
            assert 0.0 <= values["miou"] <= 1.0
    # the Markdown table: a row per arm, the synthetic label, the exact command
    with open(os.path.join(out, "results.md")) as f:
        md = f.read()
    assert "SYNTHETIC" in md and record["command"] in md
    for row in record["rows"]:
        assert f"| {row['label']} | " in md
    # the figure is a real image of the expected layout
    import matplotlib.image
    img = matplotlib.image.imread(os.path.join(out, "figure.png"))
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 300
    assert img[..., :3].std() > 0.05  # not a blank canvas


QUICK_RESULTS = os.path.join(REPO, "tests", "data", "quick_results.json")


@pytest.mark.parametrize("names", [
    DEFAULT_TABLES, pytest.param(SLOW_TABLES, marks=pytest.mark.slow)], ids=["default", "slow"])
def test_quick_results_match_the_committed_ones(quick_results, names):
    """Regeneration check: the --quick tables reproduce the numbers stored in
    tests/data/quick_results.json (a change of behaviour anywhere from the renderer to the
    metrics moves them; another CPU moves them a little, see below).

    After a change that is meant to move them (e.g. another summation order in a kernel, which
    a few training steps amplify), IRDEPTH_WRITE_QUICK_RESULTS=1 rewrites these tables' entries
    from this run instead of comparing (and the test is reported as skipped); run it with
    ``-m 'slow or not slow'`` to rewrite all seven."""
    got_tables = {}
    for name in names:
        record = quick_results[name][0]
        got_tables[name] = {row["label"]: {c: row["per_seed"]["0"][c] for c in record["columns"]}
                            for row in record["rows"]}
    with open(QUICK_RESULTS) as f:
        committed = json.load(f)
    if os.environ.get("IRDEPTH_WRITE_QUICK_RESULTS") == "1":
        committed["tables"].update(got_tables)
        with open(QUICK_RESULTS, "w") as f:
            json.dump(committed, f, indent=1)
        pytest.skip(f"IRDEPTH_WRITE_QUICK_RESULTS=1: wrote {', '.join(names)} to {QUICK_RESULTS}")
    stored = committed["tables"]
    assert sorted(stored) == sorted(TABLES)
    # XLA:CPU's float32 kernels sum in another order on another vector width (AVX2 / AVX-512),
    # and the quick runs' few training steps amplify that: two regenerations, on an AVX-512 and
    # an AVX2 machine, differed by a median 0.14 % and at most 2.6 % per figure. So: each figure
    # within 5 %, and the median change of all within 0.5 % (a change of behaviour moves many).
    changes = []
    for name, got in got_tables.items():
        assert got.keys() == stored[name].keys(), name
        for label, values in stored[name].items():
            assert got[label] == pytest.approx(values, rel=0.05, abs=1e-4), (name, label)
            changes += [abs(got[label][c] - v) / max(abs(v), 1e-4) for c, v in values.items()]
    assert np.median(changes) < 0.005, np.median(changes)


def _row(record, series, group="all"):
    return next(r for r in record["rows"] if r["series"] == series and r["group"] == group)


def test_tables_2_and_3_read_the_same_runs(quick_results):
    """Tables 2 and 3 score the same multi-task Stage I run (reconstruction vs segmentation
    columns); each single-task baseline is a run of its own."""
    t2, t3 = (quick_results[name][0] for name in DEFAULT_TABLES)
    multi = _row(t2, "multi-task (I-1 + I-2)")["per_seed"]["0"]
    assert multi["run"] == _row(t3, "multi-task")["per_seed"]["0"]["run"]
    # the single-task baselines are other runs: I-1 only (table 2), segmentation only (table 3)
    runs = {_row(t2, "single-task (I-1 only)")["per_seed"]["0"]["run"],
            _row(t3, "single-task")["per_seed"]["0"]["run"], multi["run"]}
    assert len(runs) == 3


@pytest.mark.slow
def test_runs_are_shared_between_tables(quick_results):
    """The same (config, seed) is one run: rows that read it report identical numbers."""
    r = {name: quick_results[name][0] for name in TABLES}
    hsv = _row(r["table1_preprocessing"], "HSV (ours)")["per_seed"]["0"]
    sky = _row(r["table7_sky_loss"], "with sky loss")["per_seed"]["0"]
    assert {"sky_far", "skyline_abs_rel"} <= set(sky) - set(hsv)  # table 7 adds its sky metrics
    assert {key: sky[key] for key in hsv} == hsv
    multi = _row(r["table2_multitask_reconstruction"], "multi-task (I-1 + I-2)")["per_seed"]["0"]
    assert multi == _row(r["table5_rgg_reconstruction"], "with RGG")["per_seed"]["0"]
    seg = _row(r["table3_multitask_segmentation"], "multi-task")["per_seed"]["0"]
    assert seg == _row(r["table6_rgg_segmentation"], "with RGG")["per_seed"]["0"]
    # ... and different configs are different runs with different results
    single = _row(r["table2_multitask_reconstruction"], "single-task (I-1 only)")["per_seed"]["0"]
    assert single["run"] != multi["run"] and single["psnr"] != multi["psnr"]
    ir_day = _row(r["table4_illumination"], "IR (HSV)", "day")["per_seed"]["0"]
    rgb_day = _row(r["table4_illumination"], "RGB", "day")["per_seed"]["0"]
    assert ir_day["run"] == hsv["run"] and rgb_day["run"] != hsv["run"]
    assert ir_day["count"] + _row(r["table4_illumination"], "IR (HSV)", "dusk")["per_seed"]["0"][
        "count"] + _row(r["table4_illumination"], "IR (HSV)", "night")["per_seed"]["0"][
        "count"] == hsv["count"]


def test_the_equal_length_control_trains_i1_as_many_steps_as_the_multitask_run(quick_results, quick_cache):
    """Table 2's `Arm.equal_steps` row: a Stage I-1-only run of its own whose I-1 phase has as
    many optimizer steps as the multi-task run's I-1 + I-2 (--quick: 2 + 2), said in its row."""
    record = quick_results["table2_multitask_reconstruction"][0]
    multi, short, equal = (_row(record, s) for s in ("multi-task (I-1 + I-2)", "single-task (I-1 only)",
                                                      "single-task (I-1, as many steps)"))
    assert equal["equal_steps"] and not short["equal_steps"]
    assert equal["overrides"] == ["stage1.steps_i1=4"]

    def steps(row):
        with open(os.path.join(quick_cache, "runs", row["per_seed"]["0"]["run"], "metrics.jsonl")) as f:
            logged = [r for r in map(json.loads, f) if r.get("kind") != "info"]
        return {phase: max(r["step"] for r in logged if r["stage"] == phase)
                for phase in {r["stage"] for r in logged}}

    assert steps(multi) == {"stage1_i2": 2}  # its I-1 phase is the shared I-1 run's (2 steps)
    assert steps(short) == {"stage1_i1": 2}
    assert steps(equal) == {"stage1_i1": 4}
    assert len({row["per_seed"]["0"]["run"] for row in (multi, short, equal)}) == 3


def test_runs_record_the_package_code_that_trained_them(quick_results, quick_cache, tmp_path):
    """Every run keeps the package version that trained it (`cache.CODE_FILE`, per seed in
    results.json); a run continued by other code gets both, a loud warning and a bold line in
    results.md; a run with checkpoints and no record is 'unknown' before this code."""
    record, out = quick_results["table2_multitask_reconstruction"]
    now = {"git": cache.git_commit(), "digest": cache.code_digest()}
    for row in record["rows"]:
        assert row["per_seed"]["0"]["code"] == [now]  # this session's runs: the Stage I one too
    with open(os.path.join(out, "results.md")) as f:
        assert ("package code that trained the runs read here: "
                f"code {now['digest']} (git {now['git']}): 3 runs") in f.read()

    logged = []
    ctx = types.SimpleNamespace(cache=str(tmp_path), log=logged.append)
    run = tmp_path / "runs" / "stage1-abc"
    (run / "checkpoints").mkdir(parents=True)
    cache.Context._record_code(ctx, str(run), "stage1", 0)  # resumes a run of unrecorded code
    cache.Context._record_code(ctx, str(run), "stage1", 0)  # the same code again: no new entry
    versions = cache.code_versions(str(run))
    assert versions == [{"git": "unknown", "digest": "unknown"}, now]
    assert len(logged) == 1 and "WARNING" in logged[0] and "runs/stage1-abc" in logged[0]
    same_code = {"git": "0000000", "digest": now["digest"]}  # an earlier commit, the same package
    record = {"rows": [{"per_seed": {"0": {"run": "stage1-abc", "code": versions},
                                     "1": {"run": "stage1-def", "code": [now]},
                                     "2": {"run": "stage1-ghi"}}},
                       {"per_seed": {"0": {"run": "stage1-jkl", "code": [same_code]}}}]}
    line = report._runs_code(record)
    assert f"code {now['digest']} (git {now['git']}, 0000000): 2 runs;" in line and "not recorded" in line
    assert "**resumed after the package changed" in line
    assert f"stage1-abc (code unknown (git unknown), then code {now['digest']} (git {now['git']}))" in line


def test_single_task_models_share_the_i1_weights(quick_results, quick_cache):
    """Table 2/3 protocol: multi-task and single-task Stage I runs start from one I-1 run."""
    from irdepth_jax.config import get_config
    from irdepth_jax.runs.checkpoint import restore_model
    from irdepth_jax.runs.variables import init_unet

    record = quick_results["table3_multitask_segmentation"][0]
    runs = [_row(record, s)["per_seed"]["0"]["run"] for s in ("multi-task", "single-task")]
    assert runs[0] != runs[1]
    template = init_unet(get_config("tiny"))
    copies = [restore_model(os.path.join(quick_cache, "runs", run, "checkpoints", "stage1_i1"),
                            "stage1_i1", template)[0] for run in runs]
    same = jax.tree.map(lambda a, b: bool(np.array_equal(a, b)), *copies)
    assert all(jax.tree.leaves(same))


def test_a_stage1_run_finished_with_running_averages_gets_exact_statistics(quick_results, quick_cache, tmp_path):
    """A cached Stage I run whose last checkpoints hold running-average BatchNorm statistics (as
    every run finished before `STAGE1_MODEL_VERSION` 2) gets the exact ones when a table next
    uses it, with no step trained again, and is evaluated with them: the same metrics as the
    run finished with them (they are deterministic), its training time kept."""
    from trained_runs import unfinalise

    from irdepth_experiments.cache import _unfinalised
    from irdepth_jax.config import from_dict

    name = "table2_multitask_reconstruction"
    record = quick_results[name][0]
    run = _row(record, "multi-task (I-1 + I-2)")["per_seed"]["0"]["run"]
    run_dir = os.path.join(quick_cache, "runs", run)
    with open(os.path.join(run_dir, "config.json")) as f:
        cfg = from_dict(json.load(f))
    unfinalise(run_dir, cfg, ["stage1_i2"])
    assert _unfinalised(run_dir) == ["stage1_i2"]
    for path in glob.glob(os.path.join(run_dir, "eval-*")):
        os.remove(path)
    with open(os.path.join(run_dir, "metrics.jsonl")) as f:
        steps_before = [line for line in f if '"loss"' in line]
    script = load_script(name)
    again = script.main(script.TABLE, ["--quick", "--cache", quick_cache, "--out", str(tmp_path), "--no-progress"])
    assert _unfinalised(run_dir) == []
    with open(os.path.join(run_dir, "metrics.jsonl")) as f:
        assert [line for line in f if '"loss"' in line] == steps_before
    old, new = (_row(r, "multi-task (I-1 + I-2)")["per_seed"]["0"] for r in (record, again))
    for col in record["columns"]:
        assert new[col] == pytest.approx(old[col], rel=1e-5), col


def test_rerun_is_cached_and_an_unfinished_run_resumes(quick_results, quick_cache, tmp_path):
    """A finished run is not retrained; a run without its eval file resumes (no retraining
    from scratch: the checkpoint is at the last step) and reproduces the same metrics."""
    name = "table2_multitask_reconstruction"
    record = quick_results[name][0]
    run = _row(record, "single-task (I-1 only)")["per_seed"]["0"]["run"]
    (eval_file,) = glob.glob(os.path.join(quick_cache, "runs", run, "eval-*.json"))
    os.remove(eval_file)
    script = load_script(name)
    again = script.main(script.TABLE, ["--quick", "--cache", quick_cache, "--out",
                                       str(tmp_path), "--no-progress"])
    assert os.path.exists(eval_file)
    with open(os.path.join(quick_cache, "runs", run, "metrics.jsonl")) as f:
        steps = [r["step"] for r in map(json.loads, f) if r.get("kind") != "info"]
    assert steps == sorted(set(steps)) and max(steps) == 2  # not trained a second time
    for old, new in zip(record["rows"], again["rows"]):
        for col in record["columns"]:
            assert new["per_seed"]["0"][col] == pytest.approx(old["per_seed"]["0"][col], rel=1e-5)


def test_help_explains_the_options(capsys):
    script = load_script("table1_preprocessing")
    with pytest.raises(SystemExit) as exit_info:
        script.main(script.TABLE, ["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for option in ("--preset", "--seeds", "--data", "--out", "--quick", "--set", "--cache"):
        assert option in text
    assert "SYNTHETIC" in text and "--eval-frames" in text and "MS2 protocol" in text


def test_bad_arguments_are_named():
    script = load_script("table7_sky_loss")
    with pytest.raises(SystemExit, match="unknown config key 'stage2.nope'"):
        script.main(script.TABLE, ["--quick", "--set", "stage2.nope=1", "--cache", "/nonexistent/x"])
    with pytest.raises(SystemExit):
        script.main(script.TABLE, ["--seeds", "1", "1"])


def test_summarise_hand_numbers():
    s = report.summarise([1.0, 2.0, 4.0])
    assert s["mean"] == pytest.approx(7 / 3)
    assert s["std"] == pytest.approx(math.sqrt(((1 - 7 / 3) ** 2 + (2 - 7 / 3) ** 2
                                                + (4 - 7 / 3) ** 2) / 2))
    assert s["n"] == 3
    assert report.summarise([float("nan"), 3.0]) == {"mean": 3.0, "std": 0.0, "n": 1}
    assert math.isnan(report.summarise([float("nan")])["mean"])


def test_i1_config_ignores_only_i2_settings():
    from irdepth_jax.config import apply_overrides, get_config

    base = get_config("tiny")
    single = apply_overrides(base, ["stage1.multitask=false", "stage1.w_rec=0.5"])
    assert cache.i1_config(single, base) == cache.i1_config(base, base)
    assert cache.i1_config(base, base).stage1.steps_i2 == 0
    other_i1 = apply_overrides(base, ["stage1.learning_rate=0.5"])
    assert cache.i1_config(other_i1, base) != cache.i1_config(base, base)
    no_rgg = apply_overrides(base, ["unet.use_rgg=false"])
    assert cache.i1_config(no_rgg, base) != cache.i1_config(base, base)


def test_claims_script_lists_every_claim(quick_results, tmp_path):
    """Every claim of the tables this session ran (all seven with -m slow)."""
    results = os.path.dirname(quick_results[DEFAULT_TABLES[0]][1])
    claims.main(["--results", results, "--out", str(tmp_path / "claims.md")])
    text = (tmp_path / "claims.md").read_text()
    written = json.loads((tmp_path / "claims.json").read_text())["claims"]
    expected = claims.check_claims(claims.load_results(results))
    ran = set(quick_results.done)
    assert {c.table for c in claims.CLAIMS} >= set(DEFAULT_TABLES)
    assert len(expected) == sum(c.table in ran for c in claims.CLAIMS) > 0
    assert "SYNTHETIC" in text
    assert [(w["table"], w["metric"], w["verdict"]) for w in written] == \
        [(c["table"], c["metric"], c["verdict"]) for c in expected]
    for c, w in zip(expected, written):
        assert f"| {c['claim']} | {c['table']} | {c['paper_effect']:+.4f} | {c['effect']:+.4f} [" in text
        assert f"| {c['verdict']} |" in text
        # one seed (--quick): no interval (null in the JSON), so no verdict of direction
        assert (c["verdict"] in ("undecided", "no claim") or c["verdict"].startswith("undecidable:")) \
            and w["interval"] == [None, None]
        # the effect is the difference of the table's own per-seed means
        rows = {(r["series"], r["group"]): r for r in quick_results[c["table"]][0]["rows"]}
        claim = next(k for k in claims.CLAIMS if k.text == c["claim"] and k.table == c["table"])
        sign = 1 if c["column"] in report.HIGHER_IS_BETTER else -1
        mean = sign * (rows[claim.ours]["per_seed"]["0"][c["column"]]
                       - rows[claim.baseline]["per_seed"]["0"][c["column"]])
        assert c["effect"] == pytest.approx(mean, rel=1e-4, abs=1e-6)


def test_pretrained_depth_network_plumbing(quick_cache, monkeypatch):
    """Without training: --depth-init pretrained's network becomes every Stage II run's
    depth.checkpoint (Stage I runs keep theirs), a run's cache key does not depend on where the
    cache is, and the pretraining gate is rgb_d1 >= 0.85, >= 0.15 above blank_d1, with a
    blank network that reached 0.8 x the layout bound."""
    from irdepth_experiments import depth_network

    ctx = runner.context(quick=True, cache=quick_cache)
    pretrained = os.path.join(ctx.cache, "runs", "depth-0123456789ab")
    ctx.stage2_depth_checkpoint = pretrained
    stage2, stage1 = ctx.config("stage2", (), 0), ctx.config("stage1", (), 0)
    assert stage2.depth.checkpoint == pretrained and stage1.depth.checkpoint is None
    key = os.path.basename(ctx.run_dir("stage2", stage2))
    moved = dataclasses.replace(stage2, depth=dataclasses.replace(
        stage2.depth, checkpoint=pretrained.replace(ctx.cache, "/elsewhere/cache")))
    monkeypatch.setattr(ctx, "cache", "/elsewhere/cache")
    assert os.path.basename(ctx.run_dir("stage2", moved)) == key

    recipe = depth_network.QUICK_RECIPE
    keys = [os.path.basename(c.run_dir("depth", c.config("depth", recipe.overrides("rgb"), 0), "pretraining"))
            for c in (ctx, runner.context(quick=True, cache=quick_cache, overrides=["stage1.steps_i2=5"]))]
    assert keys[0] == keys[1]  # depth runs train no UNet: the Stage I settings are not in their key

    assert depth_network.gate_passed(0.90, 0.70, 0.40) and depth_network.gate_passed(0.85, 0.70, 0.40)
    assert not depth_network.gate_passed(0.84, 0.30, 0.30)  # below 0.85
    assert not depth_network.gate_passed(0.90, 0.76, 0.40)  # less than 0.15 above blank
    assert not depth_network.gate_passed(0.90, 0.02, 0.40)  # the blank network collapsed
    assert depth_network.gate_passed(0.90, 0.33, 0.40)  # above 0.8 x the layout bound


def test_a_committed_run_is_copied_into_the_cache_instead_of_trained(quick_cache, tmp_path, monkeypatch):
    """A run committed under `cache.COMMITTED_RUNS` by its cache name (the pretrained depth
    network) is copied into a cache that lacks it and its evaluation is read, with no training;
    with --no-committed-runs the cache does not take it."""
    from irdepth_experiments import cache, depth_network

    monkeypatch.setattr(cache, "COMMITTED_RUNS", str(tmp_path))
    recipe = depth_network.Recipe(frames=24, steps=7)  # a key no other test trains
    ctx = runner.context(quick=True, cache=quick_cache)
    ctx.use_pretraining_set(recipe.frames)
    overrides = recipe.overrides("rgb")
    name = os.path.basename(ctx.run_dir("depth", ctx.config("depth", overrides, 0), ctx.pretraining_data))
    committed = tmp_path / name
    committed.mkdir()
    record = {"stage2": {"all": {"d1": 0.9}}, "run": name}
    (committed / f"eval-{ctx.eval_key}.json").write_text(json.dumps(record))
    (committed / "trained.json").write_text(json.dumps({"wall_s": 3600.0}))

    ctx.args.no_committed_runs = True
    ctx._adopt_committed(os.path.join(ctx.cache, "runs", name))
    assert not os.path.exists(os.path.join(ctx.cache, "runs", name))
    ctx.args.no_committed_runs = False
    assert ctx.result("depth", overrides, 0) == record
    assert sorted(os.listdir(os.path.join(ctx.cache, "runs", name))) == sorted(os.listdir(committed))


def test_committed_stage1_models_are_taken_by_a_fresh_cache(quick_results, quick_cache, tmp_path, monkeypatch):
    """`--commit-stage1`: the Stage I model table 7's rows started from is committed (its last
    checkpoint's weights without the optimizer state, its evaluation, a MADE_BY.md; no machine
    path), and a fresh cache takes it instead of training Stage I: the committed evaluation is
    read, no I-1 phase is trained, and a Stage II run trains on its weights. Table 3 commits its
    own rows' Stage I runs."""
    from irdepth_experiments import cache

    committed = tmp_path / "committed"
    monkeypatch.setattr(cache, "COMMITTED_RUNS", str(committed))
    monkeypatch.setattr(runner, "COMMITTED_RUNS", str(committed))
    script = load_script("table7_sky_loss")
    record = script.main(script.TABLE, ["--quick", "--cache", quick_cache, "--out", str(tmp_path / "t7"),
                                        "--no-progress", "--commit-stage1"])
    (model,) = record["stage1_models"]
    assert model["seed"] == 0 and 0 <= model["miou"] <= 1
    path = committed / model["run"]
    (step,) = os.listdir(path / "checkpoints" / "stage1_i2")
    assert "train" not in os.listdir(path / "checkpoints" / "stage1_i2" / step)
    assert "model" in os.listdir(path / "checkpoints" / "stage1_i2" / step)
    assert {"MADE_BY.md", "config.json", "trained.json"} <= set(os.listdir(path))
    assert "seed 0" in (path / "MADE_BY.md").read_text() and "--commit-stage1" in (path / "MADE_BY.md").read_text()
    assert "--out" not in (path / "MADE_BY.md").read_text()  # a scratch folder of one machine
    for name in os.listdir(path):
        if name.endswith((".json", ".md")):
            assert quick_cache not in (path / name).read_text(), name

    fresh = tmp_path / "fresh"
    fresh.mkdir()
    os.symlink(os.path.join(quick_cache, "data"), fresh / "data")  # the same rendered frames
    ctx = runner.context(quick=True, cache=str(fresh))
    evaluation = ctx.result("stage1", (), 0)
    assert evaluation["run"] == model["run"] and round(evaluation["stage1"]["all"]["miou"], 4) == model["miou"]
    stage2 = ctx.result("stage2", ("stage2.preprocessing=hsv",), 0)
    assert np.isfinite(stage2["stage2"]["all"]["d1"])
    assert not (fresh / "runs" / model["run"] / "checkpoints" / "stage1_i1").exists()
    assert not any(name.startswith("stage1_i1-") for name in os.listdir(fresh / "runs"))

    # a Stage I table commits its own rows' runs (table 3: the multi-task and single-task arms)
    script = load_script("table3_multitask_segmentation")
    record = script.main(script.TABLE, ["--quick", "--cache", quick_cache, "--out", str(tmp_path / "t3"),
                                        "--no-progress", "--commit-stage1"])
    runs = {r["per_seed"]["0"]["run"] for r in record["rows"]}
    assert len(runs) == 2 and runs <= set(os.listdir(committed))
    assert model["run"] in runs  # the multi-task arm is the model the depth rows started from
    (single,) = runs - {model["run"]}
    assert os.listdir(path / "checkpoints" / "stage1_i2") == [step]  # left as table 7 committed it
    assert "table7_sky_loss" in (path / "MADE_BY.md").read_text()
    assert not (committed / single / "checkpoints").exists()  # records only: no Stage II uses it
    assert "without weights" in (committed / single / "MADE_BY.md").read_text()

    # table 2 commits its equal-length I-1 run (records only), not the preset-length one
    script = load_script("table2_multitask_reconstruction")
    record = script.main(script.TABLE, ["--quick", "--cache", quick_cache, "--out", str(tmp_path / "t2"),
                                        "--no-progress", "--commit-stage1"])
    short, equal = (_row(record, s)["per_seed"]["0"]["run"]
                    for s in ("single-task (I-1 only)", "single-task (I-1, as many steps)"))
    assert short not in os.listdir(committed) and equal in os.listdir(committed)
    assert not (committed / equal / "checkpoints").exists()

    # a fresh cache with the same evaluation set reads a records-only run's evaluation ...
    evaluation = ctx.result("stage1_i1", ("stage1.steps_i1=4",), 0)
    assert evaluation["run"] == equal and not (fresh / "runs" / equal / "checkpoints").exists()
    # ... but does not take it where the weights are needed, and says so if it holds it
    single_cfg = ctx.config("stage1", ("stage1.multitask=false",), 0)
    assert os.path.basename(ctx.run_dir("stage1", single_cfg)) == single
    ctx._adopt_committed(str(fresh / "runs" / single), weights=True)
    assert not (fresh / "runs" / single).exists()
    ctx.result("stage1", ("stage1.multitask=false",), 0)  # its evaluation: taken
    with pytest.raises(SystemExit, match="without its weights"):
        ctx._stage1(single_cfg)


def test_commit_networks_copies_the_weights_and_records_not_the_optimizer_state(tmp_path, monkeypatch):
    """`depth_network.commit_networks`: every phase of both networks keeps its records, with
    paths inside the cache made relative to it; the pretrained network's last phase also its
    last checkpoint's weights (no `train` item, no earlier step), no other run any; each gets a
    MADE_BY.md with the command and its delta<1.25."""
    from irdepth_experiments import depth_network

    cache = tmp_path / "cache"
    records = {}
    for image, d1 in (("rgb", 0.9), ("blank", 0.4)):
        for phase in (1, 2):
            run = cache / "runs" / f"depth-{image}-{phase}"
            for step in ("5", "10"):
                for item in ("model", "train", "meta"):
                    (run / "checkpoints" / "stage2" / step / item).mkdir(parents=True)
                    (run / "checkpoints" / "stage2" / step / item / "data").write_text(item)
            for name in ("trained.json", "metrics.jsonl", "eval-abc.json", "eval-abc.npz"):
                (run / name).write_text("{}")
            checkpoint = json.dumps(str(cache / "runs" / f"depth-{image}-1") if phase == 2 else None)
            (run / "config.json").write_text(f'{{"depth": {{"checkpoint": {checkpoint}}}}}')
            (run / "tb").mkdir()
            records[image, phase] = {"run": run.name, "eval_data": "eval",
                                     "stage2": {"all": {"d1": d1 - 0.1 * (phase == 1)}}}
    info = {"height": 8, "width": 8, "scenes": "varied", "seed": 2, "made_by": "rendered"}

    def result(kind, overrides, seed):
        image = "blank" if "stage2.preprocessing=blank" in overrides else "rgb"
        return records[image, 2 if any(o.startswith("depth.checkpoint=") for o in overrides) else 1]

    ctx = types.SimpleNamespace(cache=str(cache), result=result,
                                use_pretraining_set=lambda frames: {**info, "made_by": f"rendered {frames}"})
    recipe = depth_network.Recipe(frames=6000, restarts=((8000, 5e-5, 12000),))  # two phases
    written = depth_network.commit_networks(ctx, recipe, into=str(tmp_path / "committed"), command="CMD")
    committed = {(image, phase): tmp_path / "committed" / f"depth-{image}-{phase}"
                 for image in ("rgb", "blank") for phase in (1, 2)}
    assert written == [str(committed[key]) for key in (("rgb", 1), ("rgb", 2), ("blank", 1), ("blank", 2))]
    kept = ["MADE_BY.md", "config.json", "eval-abc.json", "eval-abc.npz", "metrics.jsonl", "trained.json"]
    for key, path in committed.items():
        assert sorted(os.listdir(path)) == sorted(kept + (["checkpoints"] if key == ("rgb", 2) else [])), key
    rgb = committed["rgb", 2]
    assert os.listdir(rgb / "checkpoints" / "stage2") == ["10"]
    assert sorted(os.listdir(rgb / "checkpoints" / "stage2" / "10")) == ["meta", "model"]
    assert json.loads((rgb / "config.json").read_text())["depth"]["checkpoint"] == "runs/depth-rgb-1"
    assert depth_network.cache_relative(f"--cache {cache} data {cache}/data/x", str(cache)) == \
        "--cache <cache> data data/x"
    made_by = (rgb / "MADE_BY.md").read_text()
    assert "`CMD`" in made_by and "0.9000" in made_by and "blank: the same on a constant grey image with" in made_by
    assert "phase 2 of 2" in made_by and "then 8000 steps from it" in made_by
    assert "Pretraining data of this phase: `rendered 12000`" in made_by
    blank_made_by = (committed["blank", 1] / "MADE_BY.md").read_text()
    assert "0.3000" in blank_made_by and "Pretraining data of this phase: `rendered 6000`" in blank_made_by


def test_pilot_runs_the_three_rows_from_the_pretrained_network_and_gives_gate_3s_margins(tmp_path):
    """`depth_network.pilot`: HSV, camera-like and blank at seed 0, every Stage II from the last
    phase of the pretrained network; margins over the blank row, gates 2 and 3."""
    from irdepth_experiments import depth_network

    d1 = {"hsv": 0.62, "camera": 0.58, "blank": 0.50}
    asked = []

    def result(kind, overrides, seed):
        asked.append((kind, overrides, seed))
        if kind == "depth":
            phase = 2 if any(o.startswith("depth.checkpoint=") for o in overrides) else 1
            return {"run": f"depth-{phase}", "stage2": {"all": {"d1": 0.9}}}
        if kind == "stage1":
            return {"run": "stage1-0", "stage1": {"all": {"miou": 0.64}}, "train_wall_s": 3.0}
        image = overrides[0].split("=")[1]
        return {"run": f"stage2-{image}", "stage2": {"all": {"d1": d1[image]}}, "train_wall_s": 1.0,
                "eval_wall_s": 2.0}

    ctx = types.SimpleNamespace(cache=str(tmp_path), use_pretraining_set=lambda frames: {}, result=result)
    out = depth_network.pilot(ctx)
    assert ctx.stage2_depth_checkpoint == str(tmp_path / "runs" / "depth-2")
    assert [a for a in asked if a[0] == "stage2"] == [("stage2", o, 0) for o in depth_network.PILOT_ARMS.values()]
    assert out["HSV (ours)"]["d1"] == 0.62 and out["blank (control)"]["run"] == "stage2-blank"
    assert out["margin_over_blank"] == {"HSV (ours)": pytest.approx(0.12), "camera-like": pytest.approx(0.08)}
    assert ("stage1", (), 0) in asked and out["stage1"] == {"miou": 0.64, "run": "stage1-0", "train_wall_s": 3.0}
    assert out["gates"] == {"stage1": True, "hsv_over_blank": True}  # 0.64 >= 0.6, 0.12 >= 0.10


def test_each_restart_trains_on_its_own_pretraining_set(tmp_path):
    """`depth_network.network_phases`: each phase fine-tunes the one before it, on the frames
    its restart names (the third phase on more frames than the first two); the context is left
    on the recipe's first set (the layout bound's)."""
    from irdepth_experiments import depth_network

    recipe = depth_network.Recipe(frames=60, restarts=((8, 5e-5, 60), (8, 5e-5, 120)))
    sets, asked = [], []

    def result(kind, overrides, seed):
        asked.append((overrides, sets[-1]))
        return {"run": f"depth-{len(asked)}"}

    ctx = types.SimpleNamespace(cache=str(tmp_path), use_pretraining_set=sets.append, result=result)
    records = depth_network.network_phases(ctx, "rgb", recipe)
    assert [r["run"] for r in records] == ["depth-1", "depth-2", "depth-3"]
    assert [frames for _, frames in asked] == [60, 60, 120] and sets[-1] == 60
    assert f"depth.checkpoint={tmp_path}/runs/depth-2" in asked[2][0]
    assert "then 8 steps from it at 5e-05 (fresh optimizer, poly decay) on 120 frames" in \
        depth_network._made_by({"height": 8, "width": 8, "scenes": "varied", "seed": 2}, recipe)


def test_layout_bound_worked_by_hand():
    """Training frames at 10 m on the left half and 40 m on the right: the best constant is ~10
    and ~40 m per pixel; an evaluation frame at those depths scores 1, one at twice them 0, and
    a pixel without depth in every training frame does not count."""
    from irdepth_experiments import depth_network

    train = np.zeros((3, 2, 4), np.float32)
    train[:, :, :2], train[:, :, 2:] = 10.0, 40.0
    train[0, 0, 0] = 0.0  # one missing return
    same, double = train[1:2], 2 * train[1:2]
    assert depth_network.layout_bound(train, same) == 1.0
    assert depth_network.layout_bound(train, double) == 0.0
    mixed = same.copy()
    mixed[0, :, 2:] = 80.0  # right half wrong
    assert depth_network.layout_bound(train, mixed) == pytest.approx(0.5)


@pytest.mark.slow
def test_depth_tables_from_a_pretrained_depth_network(quick_results, quick_cache, tmp_path):
    """--depth-init pretrained: the depth network is pretrained (`irdepth train depth`) on a
    separate rendered set of visible images and every Stage II run starts from it; the results
    record the pretraining gate, and the claims of such a table are gated on it."""
    quick_results["table3_multitask_segmentation"]  # the Stage I run, shared through the cache
    script = load_script("table7_sky_loss")
    out = tmp_path / "table7_sky_loss"  # claims.load_results finds a table by its name
    record = script.main(script.TABLE, ["--quick", "--depth-init", "pretrained", "--cache", quick_cache,
                                        "--out", str(out), "--no-progress"])
    network = record["depth_network"]
    assert record["depth_init"] == "pretrained"
    assert set(network) >= {"rgb_d1", "blank_d1", "passed", "rule", "made_by"}
    assert 0 <= network["blank_d1"] <= 1 and 0 <= network["rgb_d1"] <= 1
    assert network["passed"] is False  # two steps of pretraining read nothing
    assert len(network["pretraining_data"]) == 2  # one set per phase: QUICK_RECIPE's 24 frames
    assert all(made_by.startswith("write_synthetic_dataset(path, 24, 0, ") for made_by in network["pretraining_data"])
    runs = os.path.join(quick_cache, "runs")
    for row in record["rows"]:
        with open(os.path.join(runs, row["per_seed"]["0"]["run"], "config.json")) as f:
            checkpoint = json.load(f)["depth"]["checkpoint"]
        assert os.path.basename(checkpoint).startswith("depth-"), row["label"]
        with open(os.path.join(checkpoint, "config.json")) as f:
            assert json.load(f)["stage2"]["preprocessing"] == "rgb"
    assert [r["series"] for r in record["rows"]][-1] == "blank (control)"
    records = claims.load_results(str(tmp_path))
    verdicts = [c["verdict"] for c in claims.check_claims(records)]
    assert verdicts and all(v.startswith("undecidable: pretraining gate") for v in verdicts)


def _ms2_layout(root, frames: int = 11, size=(32, 48)):
    """A tiny MS2 root: one sequence per split list (train, val, test day / night / rainy)."""
    import cv2

    rng = np.random.default_rng(0)
    root.mkdir(parents=True)
    for split in ("train", "val", "test_day", "test_night", "test_rainy"):
        seq = f"_seq_{split}"
        (root / f"{split}_list.txt").write_text(seq + "\n")
        img_dir = root / "sync_data" / seq / "thr" / "img_left"
        depth_dir = root / "proj_depth" / seq / "thr" / "depth_filtered"
        img_dir.mkdir(parents=True)
        depth_dir.mkdir(parents=True)
        for k in range(frames):
            cv2.imwrite(str(img_dir / f"{k:06d}.png"), rng.integers(3000, 6000, size).astype(np.uint16))
            depth = np.where(rng.random(size) < 0.5, rng.integers(256, 60 * 256, size), 0)
            cv2.imwrite(str(depth_dir / f"{k:06d}.png"), depth.astype(np.uint16))
    return root


@pytest.mark.slow  # about a minute on 2 cores; the MS2 reader and protocol have their own fast tests
def test_the_tables_on_a_users_ms2_dataset(quick_cache, tmp_path):
    """--data MS2_ROOT: trained on its train list, evaluated with the MS2 protocol: every 10th
    frame of the three test lists, median-scaled, one group per test condition."""
    root = _ms2_layout(tmp_path / "ms2")
    script = load_script("table7_sky_loss")
    record = script.main(script.TABLE, [
        "--quick", "--data", str(root), "--cache", quick_cache, "--out", str(tmp_path / "out"),
        "--no-progress", "--set", "stage1.seg_labels=synthetic", "stage1.synthetic_labeled=8"])
    assert record["synthetic"] is False and record["data"]["format"] == "ms2"
    assert record["protocol"] == {"name": "ms2", "stride": 10, "align": "median"}
    assert [r["series"] for r in record["rows"]] == ["without sky loss", "with sky loss", "blank (control)"]
    assert [r["per_seed"]["0"]["count"] for r in record["rows"]] == [4, 4, 4]  # 33 frames [0:-1:10]
    md = (tmp_path / "out" / "results.md").read_text()
    assert "SYNTHETIC" not in md and "ms2 protocol (every 10th frame, alignment median)" in md
    run = record["rows"][0]["per_seed"]["0"]["run"]
    (eval_file,) = glob.glob(os.path.join(quick_cache, "runs", run, "eval-*.json"))
    with open(eval_file) as f:
        groups = json.load(f)["stage2"]
    # frames 0, 10 (day list), 20 (night), 30 (rainy)
    assert {g: groups[g]["count"] for g in ("day", "night", "rainy")} == {"day": 2, "night": 1,
                                                                           "rainy": 1}


def test_the_tables_on_a_users_folder_dataset(quick_results, quick_cache, tmp_path):
    """--data FOLDER: trained on its train split, evaluated on its own test split. The folder's
    frames are of the quick tables' size (the suite's), so that its runs (new ones: other data)
    take the train steps those tables compiled."""
    from trained_runs import DATA

    from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset

    quick_results["table2_multitask_reconstruction"]  # the compiled steps of its quick runs
    folder = write_synthetic_dataset(tmp_path / "folder", **{**DATA, "seed": 5}, progress=False)
    script = load_script("table2_multitask_reconstruction")
    record = script.main(script.TABLE, ["--quick", "--data", str(folder), "--cache",
                                        quick_cache, "--out", str(tmp_path / "out"), "--no-progress"])
    assert record["synthetic"] is False and record["data"]["format"] == "folder"
    assert record["protocol"] == {"name": "folder", "stride": 1, "align": None}
    assert record["eval_data"]["path"] == str(folder)
    runs = {r["per_seed"]["0"]["run"] for r in record["rows"]}
    assert not runs & {r["per_seed"]["0"]["run"] for r in quick_results[
        "table2_multitask_reconstruction"][0]["rows"]}  # trained on the folder: runs of their own
    test_frames = sum(r["split"] == "test" for r in
                      json.loads((folder / "manifest.json").read_text())["frames"])
    assert all(r["per_seed"]["0"]["count"] == test_frames for r in record["rows"])
    assert "SYNTHETIC" not in (tmp_path / "out" / "results.md").read_text()


@pytest.mark.slow
def test_table4_controls(quick_results):
    """Table 4's blank-image control is its own run; the median-scaled rows re-read the IR /
    RGB runs (same run, other alignment)."""
    record = quick_results["table4_illumination"][0]
    blank = _row(record, "blank (control)", "day")["per_seed"]["0"]
    ir, ir_median = (_row(record, s, "day")["per_seed"]["0"] for s in ("IR (HSV)", "IR (HSV), median-scaled"))
    assert blank["run"] != ir["run"] and ir_median["run"] == ir["run"]
    assert ir_median["count"] == ir["count"] and ir_median["d1"] != ir["d1"]


@pytest.mark.slow
def test_pipeline_figure_quick(quick_results, quick_cache, tmp_path):
    """experiments/pipeline_figure.py draws the quick HSV run (cached by the tables)."""
    quick_results["table1_preprocessing"]  # trains (or finds) the quick HSV run in the cache
    out = tmp_path / "pipeline.png"
    load_script("pipeline_figure").main(["--quick", "--cache", quick_cache, "--out", str(out)])
    import matplotlib.image
    img = matplotlib.image.imread(str(out))
    assert img.shape[0] > 300 and img.shape[1] > 800  # 3 condition rows x 7 panels
    assert img[..., :3].std() > 0.05
