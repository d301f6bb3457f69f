"""`irdepth train depth`: Depth Anything V2 trained on visible images with depth, and a Stage II
started from that run through depth.checkpoint=RUN_DIR as from a released checkpoint."""

import json

import jax
import numpy as np
import pytest
from trained_runs import QUICK

from irdepth_jax import cli
from irdepth_jax.config import apply_overrides, get_config
from irdepth_jax.data.folder import FolderDataset
from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset
from irdepth_jax.errors import RunError
from irdepth_jax.runs.variables import init_depth, load_model


@pytest.fixture(scope="module")
def depth_run(synthetic_data, tmp_path_factory):
    """A depth pretraining run of 2 steps on the shared synthetic dataset's visible images."""
    work = tmp_path_factory.mktemp("depth") / "run"
    assert cli.main(["train", "depth", "--data", str(synthetic_data), "--workdir", str(work),
                     "--steps", "2", *QUICK]) == 0
    return work


def test_train_depth_trains_on_the_visible_images(depth_run, capsys):
    with open(depth_run / "config.json") as f:
        cfg = json.load(f)
    assert cfg["stage2"]["preprocessing"] == "rgb" and cfg["stage2"]["sky_loss"] is False
    with open(depth_run / "metrics.jsonl") as f:
        lines = [json.loads(ln) for ln in f]
    info = {k: v for ln in lines if ln.get("kind") == "info" for k, v in ln.items()}
    assert info["input"] == "rgb" and info["sky_loss"] == "off" and "stage1" not in info
    losses = [ln["loss"] for ln in lines if "loss" in ln]
    assert len(losses) == 2 and all(np.isfinite(losses))


def test_train_depth_on_a_blank_image_is_the_pretraining_control(synthetic_data, depth_run,
                                                                   tmp_path):
    """stage2.preprocessing=blank: the same training on a constant grey image (the pretraining
    gate's control), recorded as such. As long as `depth_run`: the same program (an image fed
    from the host, the same decay schedule), which that run compiled."""
    work = tmp_path / "blank"
    assert cli.main(["train", "depth", "--data", str(synthetic_data), "--workdir", str(work),
                     "--steps", "2", *QUICK, "stage2.preprocessing=blank"]) == 0
    with open(work / "config.json") as f:
        assert json.load(f)["stage2"]["preprocessing"] == "blank"
    with open(work / "metrics.jsonl") as f:
        info = {k: v for ln in map(json.loads, f) if ln.get("kind") == "info" for k, v in ln.items()}
    assert info["input"] == "blank"


def test_stage2_starts_from_a_depth_run_as_from_a_released_checkpoint(depth_run):
    """depth.checkpoint=RUN_DIR: backbone and (same kind) head are the run's final params; a
    relative head is started fresh, as from a released checkpoint of the other kind."""
    _, stage, trained = load_model(str(depth_run))
    assert stage == "stage2"
    cfg = apply_overrides(get_config("tiny"), [f"depth.checkpoint={depth_run}"])
    params, described = init_depth(cfg)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(trained["depth"]), strict=True):
        np.testing.assert_array_equal(a, b)
    assert described["head"].startswith(f"loaded from {depth_run} (metric")
    relative, described = init_depth(apply_overrides(cfg, ["depth.metric=false"]))
    np.testing.assert_array_equal(jax.tree.leaves(relative["pretrained"])[0],
                                  jax.tree.leaves(trained["depth"]["pretrained"])[0])
    assert described["head"].startswith("random init")
    # train_stage2 starts from init_depth(cfg); a 1-step Stage II from a depth run, by the CLI,
    # was checked by hand (47 s: "backbone: loaded from RUN (encoder tiny)")


def test_a_depth_checkpoint_of_another_architecture_or_stage_is_refused(depth_run, stage1_run):
    with pytest.raises(RunError, match="trained with depth.encoder=tiny, this run has depth.encoder=small"):
        init_depth(apply_overrides(get_config("tiny"), [f"depth.checkpoint={depth_run}",
                                                        "depth.encoder=small"]))
    with pytest.raises(RunError, match="which has no depth network"):
        init_depth(apply_overrides(get_config("tiny"), [f"depth.checkpoint={stage1_run}"]))


def test_train_depth_refuses_data_without_visible_images_and_thermal_settings(tmp_path, capsys,
                                                                              synthetic_data):
    ds = write_synthetic_dataset(tmp_path / "ds", n=6, labeled=0, height=32, width=48, seed=2,
                                 progress=False)
    doc = json.loads((ds / "manifest.json").read_text())
    k = next(i for i, r in enumerate(doc["frames"]) if r["split"] == "train")
    doc["frames"][k]["has_rgb"] = False  # as a thermal-only dataset (MS2) is read
    (ds / "manifest.json").write_text(json.dumps(doc))
    assert FolderDataset(ds)[k]["has_rgb"] is False
    args = ["train", "depth", "--data", str(ds), "--workdir", str(tmp_path / "w"), "--steps", "1", *QUICK]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "have no visible image" in err and doc["frames"][k]["id"] in err
    assert not (tmp_path / "w" / "checkpoints").exists()
    for extra, message in ((["stage2.preprocessing=he"], "train depth trains on the visible images"),
                           (["--stage1-checkpoint", str(tmp_path)], "--stage1-checkpoint is for train stage2")):
        assert cli.main(["train", "depth", "--data", str(synthetic_data), "--workdir",
                         str(tmp_path / "x"), "--steps", "1", *QUICK, *extra]) == 2
        assert message in capsys.readouterr().err
