"""The ablation scripts (experiments/table*.py) in --quick mode, and the runner's bookkeeping.

All scripts run in this process against one session-wide cache (dataset, runs, XLA
compilation cache), so the Stage I model of the quick config is trained once and shared by the
tables, as it is for the real runs.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import sys

import jax
import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXPERIMENTS = os.path.join(REPO, "experiments")
TABLES = ("table1_preprocessing", "table2_multitask_reconstruction",
          "table3_multitask_segmentation", "table4_illumination", "table5_rgg_reconstruction",
          "table6_rgg_segmentation", "table7_sky_loss")


def load_runner():
    """experiments/runner.py as the module `runner` (how the table scripts import it)."""
    if EXPERIMENTS not in sys.path:
        sys.path.insert(0, EXPERIMENTS)
    return importlib.import_module("runner")


def load_script(name: str):
    """Imports experiments/<name>.py."""
    load_runner()
    spec = importlib.util.spec_from_file_location(f"experiments_{name}",
                                                  os.path.join(EXPERIMENTS, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def quick_cache_dir(tmp_path_factory) -> str:
    """The session's experiment cache (also used by tests/test_notebooks.py)."""
    return str(tmp_path_factory.getbasetemp() / "experiments_cache")


@pytest.fixture(scope="session")
def quick_cache(tmp_path_factory):
    """Dataset and runs in a fresh temporary cache (compiled steps go to the test run's XLA
    cache, see conftest.py)."""
    return quick_cache_dir(tmp_path_factory)


@pytest.fixture(scope="session")
def quick_results(quick_cache, tmp_path_factory):
    """name -> (results.json record, output dir) of every table in --quick mode."""
    out_root = tmp_path_factory.mktemp("experiment_results")
    results = {}
    for name in TABLES:
        out = str(out_root / name)
        load_script(name).main(load_script(name).TABLE,
                               ["--quick", "--cache", quick_cache, "--out", out, "--no-progress"])
        with open(os.path.join(out, "results.json")) as f:
            results[name] = (json.load(f), out)
    return results


def finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


@pytest.mark.parametrize("name", TABLES)
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


def _row(record, series, group="all"):
    return next(r for r in record["rows"] if r["series"] == series and r["group"] == group)


def test_runs_are_shared_between_tables(quick_results):
    """The same (config, seed) is one run: rows that read it report identical numbers."""
    r = {name: rec for name, (rec, _) in quick_results.items()}
    hsv = _row(r["table1_preprocessing"], "HSV (ours)")["per_seed"]["0"]
    assert hsv == _row(r["table7_sky_loss"], "with sky loss")["per_seed"]["0"]
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


def test_single_task_models_share_the_i1_weights(quick_results, quick_cache):
    """Table 2/3 protocol: multi-task and single-task Stage I runs start from one I-1 run."""
    from irdepth_jax.config import get_config
    from irdepth_jax.train.checkpoint import restore_model
    from irdepth_jax.train.variables import init_unet

    record = quick_results["table3_multitask_segmentation"][0]
    runs = [_row(record, s)["per_seed"]["0"]["run"] for s in ("multi-task", "single-task")]
    assert runs[0] != runs[1]
    template = init_unet(get_config("tiny"))
    copies = [restore_model(os.path.join(quick_cache, "runs", run, "checkpoints", "stage1_i1"),
                            "stage1_i1", template)[0] for run in runs]
    same = jax.tree.map(lambda a, b: bool(np.array_equal(a, b)), *copies)
    assert all(jax.tree.leaves(same))


def test_rerun_is_cached_and_an_unfinished_run_resumes(quick_results, quick_cache, tmp_path):
    """A finished run is not retrained; a run without its eval file resumes (no retraining
    from scratch: the checkpoint is at the last step) and reproduces the same metrics."""
    record = quick_results["table7_sky_loss"][0]
    run = _row(record, "without sky loss")["per_seed"]["0"]["run"]
    eval_file = os.path.join(quick_cache, "runs", run, "eval_test.json")
    os.remove(eval_file)
    script = load_script("table7_sky_loss")
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
    assert "SYNTHETIC" in text


def test_bad_arguments_are_named():
    script = load_script("table7_sky_loss")
    with pytest.raises(SystemExit, match="unknown config key 'stage2.nope'"):
        script.main(script.TABLE, ["--quick", "--set", "stage2.nope=1", "--cache", "/nonexistent/x"])
    with pytest.raises(SystemExit):
        script.main(script.TABLE, ["--seeds", "1", "1"])


def test_summarise_hand_numbers():
    runner = load_runner()
    s = runner.summarise([1.0, 2.0, 4.0])
    assert s["mean"] == pytest.approx(7 / 3)
    assert s["std"] == pytest.approx(math.sqrt(((1 - 7 / 3) ** 2 + (2 - 7 / 3) ** 2
                                                + (4 - 7 / 3) ** 2) / 2))
    assert s["n"] == 3
    assert runner.summarise([float("nan"), 3.0]) == {"mean": 3.0, "std": 0.0, "n": 1}
    assert math.isnan(runner.summarise([float("nan")])["mean"])


def test_i1_config_ignores_only_i2_settings():
    runner = load_runner()
    from irdepth_jax.config import apply_overrides, get_config

    base = get_config("tiny")
    single = apply_overrides(base, ["stage1.multitask=false", "stage1.w_rec=0.5"])
    assert runner.i1_config(single, base) == runner.i1_config(base, base)
    assert runner.i1_config(base, base).stage1.steps_i2 == 0
    other_i1 = apply_overrides(base, ["stage1.learning_rate=0.5"])
    assert runner.i1_config(other_i1, base) != runner.i1_config(base, base)
    no_rgg = apply_overrides(base, ["unet.use_rgg=false"])
    assert runner.i1_config(no_rgg, base) != runner.i1_config(base, base)


def test_check_claims_signs_and_verdicts():
    """Hand-made two-row records: a lower-is-better column counts a decrease as agreement."""
    runner = load_runner()
    claim = runner.Claim("t", "A beats B (AbsRel)", ("A", "all"), ("B", "all"), "abs_rel",
                         ("A", "B"))
    record = {"rows": [
        {"series": "A", "group": "all", "per_seed": {"0": {"abs_rel": 0.10}, "1": {"abs_rel": 0.30}}},
        {"series": "B", "group": "all", "per_seed": {"0": {"abs_rel": 0.20}, "1": {"abs_rel": 0.20}}}],
        "paper": {"A": {"abs_rel": 0.05}, "B": {"abs_rel": 0.08}}}
    (out,) = runner.check_claims({"t": record}, [claim])
    assert out["diff_mean"] == pytest.approx(0.0) and out["n"] == 2
    assert out["diff_std"] == pytest.approx(math.sqrt(0.02))  # diffs +0.1 and -0.1
    assert out["agree"] == 1 and out["verdict"] == "mixed"
    assert out["paper_diff"] == pytest.approx(0.03)
    record["rows"][0]["per_seed"]["1"]["abs_rel"] = 0.15
    assert runner.check_claims({"t": record}, [claim])[0]["verdict"] == "holds"


def test_claims_script_lists_every_claim(quick_results, tmp_path):
    claims = load_script("claims")
    results = os.path.dirname(next(iter(quick_results.values()))[1])
    claims.main(["--results", results, "--out", str(tmp_path / "claims.md")])
    text = (tmp_path / "claims.md").read_text()
    runner = load_runner()
    expected = runner.check_claims(runner.load_results(results))
    assert len(expected) == len(runner.CLAIMS)
    assert "SYNTHETIC" in text
    for c in expected:
        assert f"| {c['claim']} | {c['table']} | {c['diff_mean']:+.4f}" in text


def test_pipeline_figure_quick(quick_results, quick_cache, tmp_path):
    """experiments/pipeline_figure.py draws the quick HSV run (cached by the tables)."""
    out = tmp_path / "pipeline.png"
    load_script("pipeline_figure").main(["--quick", "--cache", quick_cache, "--out", str(out)])
    import matplotlib.image
    img = matplotlib.image.imread(str(out))
    assert img.shape[0] > 300 and img.shape[1] > 800  # 3 condition rows x 7 panels
    assert img[..., :3].std() > 0.05
