"""Exact BatchNorm statistics at the end of each Stage I phase (`train.batch_statistics`)."""

import json
import os

import jax
import numpy as np
import pytest
from trained_runs import copy_run

from irdepth_jax.config import from_dict, get_config
from irdepth_jax.models.pipeline import unet_input
from irdepth_jax.models.unet import MTSAUNet
from irdepth_jax.runs.checkpoint import FINALIZED, REPLACED, Checkpointer, read_meta, restore_model
from irdepth_jax.runs.variables import init_unet, load_model, statistics_warnings, unet_shapes
from irdepth_jax.train.batch_statistics import phase_batch_stats, recompute_batch_stats

PHASES = ("stage1_i1", "stage1_i2")


def _close(a, b, atol=1e-6) -> bool:
    return all(jax.tree.leaves(jax.tree.map(lambda x, y: np.allclose(x, y, atol=atol), a, b)))


def test_recomputed_statistics_are_each_batchnorms_exact_statistics():
    """From one batch, eval mode with the recomputed statistics computes what train mode (the
    batch's own statistics) computes on it; from two batches the statistics are their mean."""
    cfg = get_config("tiny")
    variables = init_unet(cfg)
    raw = np.random.default_rng(0).uniform(2000, 9000, (4, 32, 48)).astype(np.float32)
    stats, used = recompute_batch_stats(cfg, variables, [{"raw14": raw}])
    assert used == 4 and not _close(stats, variables["batch_stats"])
    model = MTSAUNet(cfg.unet)
    train_mode, _ = model.apply(variables, unet_input(raw, cfg), train=True, mutable=["batch_stats"])
    eval_mode = model.apply({"params": variables["params"], "batch_stats": stats},
                            unet_input(raw, cfg), train=False)
    for key in ("recon", "seg_logits", "saturation"):
        np.testing.assert_allclose(eval_mode[key], train_mode[key], rtol=1e-4, atol=2e-5)
    both, used = recompute_batch_stats(cfg, variables, [{"raw14": raw[:2]}, {"raw14": raw[2:]}])
    first, second = (recompute_batch_stats(cfg, variables, [{"raw14": r}])[0] for r in (raw[:2], raw[2:]))
    assert used == 4 and _close(both, jax.tree.map(lambda a, b: (a + b) / 2, first, second))
    with pytest.raises(ValueError, match="no batch"):
        recompute_batch_stats(cfg, variables, [])


def _phase_model(run, phase, cfg):
    return restore_model(os.path.join(run, "checkpoints", phase), phase, unet_shapes(cfg))


def _config(run):
    with open(os.path.join(run, "config.json")) as f:
        return from_dict(json.load(f))


def test_each_stage1_phase_ends_with_the_statistics_of_its_final_weights(stage1_run, synthetic_data):
    """The last checkpoint of I-1 and of I-2 holds the statistics `phase_batch_stats` computes
    from that checkpoint's weights on the phase's training frames, and says so in its meta."""
    from irdepth_jax.data.source import DataSource, phase_frames

    cfg = _config(stage1_run)
    source = DataSource(str(synthetic_data))
    for phase in PHASES:
        model, meta = _phase_model(stage1_run, phase, cfg)
        record = meta[FINALIZED]
        assert record["recomputed"] and record["frames"] > 0, record
        dataset, idx = phase_frames(source, phase, cfg)
        expected, again = phase_batch_stats(cfg, dataset, idx, phase)(model)
        assert again == record and _close(model["batch_stats"], expected)


def test_resuming_a_run_finished_without_them_computes_them(stage1_run, synthetic_data, tmp_path):
    """A run whose last checkpoints hold running averages (as runs finished before this change)
    gets the exact statistics when resumed, in the same step folders, with nothing retrained."""
    from trained_runs import train, unfinalise

    run = copy_run(stage1_run, tmp_path / "run")
    cfg = _config(run)
    finalised = {phase: _phase_model(run, phase, cfg)[0]["batch_stats"] for phase in PHASES}
    unfinalise(run, cfg, PHASES)
    for phase in PHASES:
        assert FINALIZED not in read_meta(str(run / "checkpoints" / phase))
    (warning,) = load_model(str(run))[2]["warnings"]
    assert "running averages" in warning and "`resume`" in warning
    with open(run / "metrics.jsonl") as f:
        steps_before = [json.loads(line) for line in f if '"loss"' in line]
    train("stage1", synthetic_data, run, "--resume")
    assert load_model(str(run))[2]["warnings"] == []
    with open(run / "metrics.jsonl") as f:
        assert [json.loads(line) for line in f if '"loss"' in line] == steps_before  # no step again
    for phase in PHASES:
        model, meta = _phase_model(run, phase, cfg)
        assert FINALIZED in meta and _close(model["batch_stats"], finalised[phase])
        assert not any(n.endswith(REPLACED) for n in os.listdir(run / "checkpoints" / phase))


def test_a_stage2_model_says_whether_its_stage1_statistics_were_exact(stage2_run):
    """A Stage II run records the statistics record of the Stage I model it trained on; a Stage II
    of an older version (none recorded) is warned about, one without a Stage I model is not."""
    cfg, stage, model = load_model(str(stage2_run))
    assert stage == "stage2" and model["warnings"] == []
    assert model["trained_on"]["stage1_batch_stats"]["recomputed"]
    older = {"stage": "stage2", "trained_on": {"stage1": model["trained_on"]["stage1"]}}
    (warning,) = statistics_warnings("RUN", older)
    assert warning.startswith("RUN: ") and "running averages" in warning
    assert statistics_warnings("RUN", {"stage": "stage2", "trained_on": {"stage1": None}}) == []


def test_a_replace_cut_short_keeps_the_step(stage1_run, tmp_path):
    """A step moved aside by a `Checkpointer.replace` that was killed is put back by the next
    Checkpointer on the directory; one already rewritten drops the aside copy."""
    run = copy_run(stage1_run, tmp_path / "run")
    directory = run / "checkpoints" / "stage1_i2"
    step = Checkpointer(str(directory), "stage1_i2", read_only=True).latest_step()
    os.rename(directory / str(step), directory / f"{step}{REPLACED}")
    assert Checkpointer(str(directory), "stage1_i2").latest_step() == step
    assert not (directory / f"{step}{REPLACED}").exists()
    (directory / f"{step}{REPLACED}").mkdir()
    Checkpointer(str(directory), "stage1_i2")
    assert not (directory / f"{step}{REPLACED}").exists() and (directory / str(step)).is_dir()
