"""Renamed things still load: checkpoints with the gradient branch's old module names
(``dec_grad_up<i>``, ``head_saturation``) and the old optimizer group ``frozen``, and configs
with the old key ``stage1.stage12_learning_rate``."""

import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from irdepth_jax.config import (
    DeprecatedKeyWarning,
    apply_overrides,
    from_dict,
    get_config,
    to_dict,
    upgrade_dict,
)
from irdepth_jax.runs.checkpoint import Checkpointer, restore_items
from irdepth_jax.runs.variables import init_unet
from irdepth_jax.train.state import NO_UPDATE, TrainState, stage1_optimizer

CFG = apply_overrides(get_config("tiny"), ["stage1.multitask=false"])  # has the no_update group


def old_names(tree):
    """`tree` under the names the code used before the renames (what its checkpoints hold)."""
    def old(key):
        return {NO_UPDATE: "frozen"}.get(key, key)

    if isinstance(tree, dict):
        return {old(k): old_names(v) for k, v in tree.items()}
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):
        return type(tree)(*map(old_names, tree))
    if isinstance(tree, (tuple, list)):
        return type(tree)(map(old_names, tree))
    return tree


def assert_trees_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    jax.tree.map(lambda x, y: np.testing.assert_array_equal(np.asarray(x), np.asarray(y)), a, b)


@pytest.fixture(scope="module")
def stage1_state():
    """A single-task I-2 state after one update (distinct values in params and optimizer)."""
    unet = init_unet(CFG)
    tx, lr_fns = stage1_optimizer(CFG, "stage1_i2")
    state = TrainState.create(unet["params"], unet["batch_stats"], tx, jax.random.PRNGKey(0),
                              lr_fns)
    grads = jax.tree.map(lambda p: jnp.full_like(p, 0.5), state.params)
    return state.apply_gradients(grads, jax.tree.map(lambda s: s + 1.0, state.batch_stats))


def test_the_new_names_are_the_ones_in_use(stage1_state):
    assert set(stage1_state.opt_state.inner_states) == {"seg", "shared", NO_UPDATE}
    # the gradient branch's modules keep their names (Flax's init RNG depends on them)
    assert {"head_saturation", "dec_grad_up0"} <= set(stage1_state.params)


def test_an_old_stage1_checkpoint_resumes_under_the_new_names(tmp_path, stage1_state):
    legacy = stage1_state.replace(params=old_names(stage1_state.params),
                                  batch_stats=old_names(stage1_state.batch_stats),
                                  opt_state=old_names(stage1_state.opt_state))
    ckpt = Checkpointer(str(tmp_path), "stage1_i2")
    ckpt.save(1, legacy, {"config": to_dict(CFG)}, force=True)
    ckpt.wait()
    stored = json.loads((tmp_path / "1" / "train" / "_METADATA").read_text())
    for old in ("'frozen'", "'head_saturation'", "'dec_grad_up0'"):  # what old checkpoints hold
        assert any(old in k for k in stored["tree_metadata"]), old
    template = stage1_state.replace(step=jnp.zeros((), jnp.int32))
    restored, meta = ckpt.restore(template)
    assert meta["step"] == 1 and int(restored.step) == 1
    assert_trees_equal(restored.params, stage1_state.params)
    assert_trees_equal(restored.batch_stats, stage1_state.batch_stats)
    assert_trees_equal(restored.opt_state, stage1_state.opt_state)
    ckpt.close()
    # the read-only path of Stage II / eval / predict: model weights only
    items, _ = restore_items(str(tmp_path), "stage1_i2", {"model": init_unet(CFG)})
    assert_trees_equal(items["model"]["params"], stage1_state.params)


def test_an_old_stage2_checkpoint_gives_its_stage1_model_new_names(tmp_path, stage1_state):
    depth = TrainState.create({"depth_head": {"w": jnp.ones(3)}}, {}, optax.sgd(0.1),
                              jax.random.PRNGKey(0))
    unet = {"params": stage1_state.params, "batch_stats": stage1_state.batch_stats}
    ckpt = Checkpointer(str(tmp_path), "stage2")
    ckpt.save(3, depth, {}, frozen={"unet": old_names(unet)}, force=True)
    ckpt.wait()
    ckpt.close()
    templates = {"model": {"params": {"depth_head": {"w": jnp.zeros(3)}}, "batch_stats": {}},
                 "frozen": {"unet": init_unet(CFG)}}
    items, _ = restore_items(str(tmp_path), "stage2", templates)
    assert_trees_equal(items["frozen"]["unet"], unet)
    np.testing.assert_array_equal(items["model"]["params"]["depth_head"]["w"], np.ones(3))


# --------------------------------------------------------------------------- config keys
def test_old_config_key_in_a_stored_config_maps_silently():
    stored = to_dict(get_config("tiny"))
    stored["stage1"]["stage12_learning_rate"] = stored["stage1"].pop("i2_learning_rate") * 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cfg = from_dict(stored)
    assert cfg.stage1.i2_learning_rate == 2 * get_config("tiny").stage1.i2_learning_rate


def test_old_config_key_in_an_override_warns_and_sets_the_new_one():
    with pytest.warns(DeprecatedKeyWarning, match="'stage1.i2_learning_rate'"):
        cfg = apply_overrides(get_config("tiny"), ["stage1.stage12_learning_rate=0.25"])
    assert cfg.stage1.i2_learning_rate == 0.25


def test_old_and_new_config_key_together_are_refused():
    with pytest.raises(ValueError, match="give only 'stage1.i2_learning_rate'"):
        upgrade_dict({"stage1": {"stage12_learning_rate": 0.1, "i2_learning_rate": 0.2}})
    with pytest.warns(DeprecatedKeyWarning, match="x.json"):
        assert upgrade_dict({"stage1": {"stage12_learning_rate": 0.1}}, where="x.json") == {
            "stage1": {"i2_learning_rate": 0.1}}


def test_cli_config_files_with_the_old_key(tmp_path, capsys):
    from irdepth_jax import cli

    doc = tmp_path / "c.json"
    doc.write_text(json.dumps({"stage1": {"stage12_learning_rate": 0.125}}))
    with pytest.warns(DeprecatedKeyWarning, match="c.json"):
        assert cli.load_config("tiny", str(doc), []).stage1.i2_learning_rate == 0.125
    py = tmp_path / "c.py"
    py.write_text("import dataclasses\nfrom irdepth_jax.config import get_config\n"
                  "c = get_config('tiny')\n"
                  "config = dataclasses.replace(c, stage1=dataclasses.replace(c.stage1, "
                  "stage12_learning_rate=0.5))\n")
    with pytest.raises(cli.CliError, match="'stage1.stage12_learning_rate' is now "
                                           "'stage1.i2_learning_rate'"):
        cli.load_config("tiny", str(py), [])


def test_cli_prints_the_deprecation_in_one_line(tmp_path, capsys):
    from irdepth_jax import cli

    code = cli.main(["train", "stage1", "--data", str(tmp_path), "--workdir",
                     str(tmp_path / "w"), "stage1.stage12_learning_rate=0.5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[0].startswith("irdepth: warning: override 'stage1.stage12_learning_rate=0.5': "
                             "config key 'stage1.stage12_learning_rate' is deprecated, use "
                             "'stage1.i2_learning_rate'")
    assert err[1].startswith("irdepth: error: ") and len(err) == 2


def test_resuming_a_run_whose_config_json_has_the_old_key(tmp_path):
    from irdepth_jax.train.runlog import prepare_workdir

    cfg = get_config("tiny")
    stored = to_dict(cfg)
    stored["stage1"]["stage12_learning_rate"] = stored["stage1"].pop("i2_learning_rate")
    (tmp_path / "config.json").write_text(json.dumps(stored))
    prepare_workdir(str(tmp_path), cfg, resume=True)  # the same run: no "config differs"


def test_legacy_names_rename_only_what_was_renamed():
    from irdepth_jax.runs.legacy_names import from_legacy, has_legacy_keys, to_legacy

    state = optax.MaskedState(inner_state={"dec_grad_up12": 1, "head_saturation": 2,
                                           "frozen": 3, "dec_grad": 4})
    tree = {"opt": {"inner_states": {"frozen": 5}}, "state": state}
    new = from_legacy(tree)
    assert new == {"opt": {"inner_states": {"no_update": 5}},  # a group only under inner_states
                   "state": optax.MaskedState(inner_state={"dec_grad_up12": 1,
                                                           "head_saturation": 2, "frozen": 3,
                                                           "dec_grad": 4})}
    assert type(new["state"]) is optax.MaskedState
    assert to_legacy(new) == tree
    assert has_legacy_keys(tree) and not has_legacy_keys(new)
    assert not has_legacy_keys({"x": {"frozen": 1}, "y": [{"dec_seg_up0": 2}]})


def test_the_legacy_group_name_maps_to_the_optimizer_group_of_today():
    """`runs.legacy_names` (which imports nothing of train/) names the group `train.state` uses."""
    from irdepth_jax.runs.legacy_names import LEGACY_GROUP_NAMES
    from irdepth_jax.train.state import NO_UPDATE

    assert dict(LEGACY_GROUP_NAMES)["frozen"] == NO_UPDATE
