"""Stage II's start from released Depth Anything V2 files (`init_depth`): which parts are loaded
(depth.checkpoint_kind, depth.load_head) and how it is described."""

import jax
import numpy as np
import pytest
from da_params import random_params

from irdepth_jax.config import apply_overrides, get_config
from irdepth_jax.errors import RunError
from irdepth_jax.models.depth_anything import depth_anything_config
from irdepth_jax.runs.variables import init_depth, random_depth
from irdepth_jax.weights import to_official_state_dict

torch = pytest.importorskip("torch")

RELATIVE = "depth_anything_v2_vits.pth"
HYPERSIM = "depth_anything_v2_metric_hypersim_vits.pth"
VKITTI = "depth_anything_v2_metric_vkitti_vits.pth"
UNNAMED = "finetuned.pth"


@pytest.fixture(scope="module")
def released(tmp_path_factory):
    """({name: path}, params): the same random tiny-encoder weights as plain official state
    dicts under the official names (the file cannot tell a relative head from a metric one)."""
    params = random_params(depth_anything_config("tiny"), seed=3)
    state = {k: torch.from_numpy(v) for k, v in to_official_state_dict(params).items()}
    folder = tmp_path_factory.mktemp("released")
    for name in (RELATIVE, HYPERSIM, VKITTI, UNNAMED):
        torch.save(state, folder / name)
    return {name: str(folder / name) for name in (RELATIVE, HYPERSIM, VKITTI, UNNAMED)}, params


def start(path, *overrides):
    """(cfg, params, description) of a tiny-preset Stage II (depth.metric=true, max_depth 80)."""
    cfg = apply_overrides(get_config("tiny"), [f"depth.checkpoint={path}", *overrides])
    return (cfg, *init_depth(cfg))


def assert_same(a, b):
    jax.tree.map(np.testing.assert_array_equal, a, b)


def test_relative_file_for_a_metric_run_gives_the_backbone_only(released):
    paths, params = released
    path = paths[RELATIVE]
    cfg, got, info = start(path)
    assert_same(got["pretrained"], params["pretrained"])
    assert_same(got["depth_head"], random_depth(cfg)["depth_head"])
    assert info == {"backbone": f"loaded from {path} (encoder tiny)",
                    "head": f"random init: {path} holds a relative head, depth.metric=true "
                            "trains a metric one (backbone only, as the official metric "
                            "fine-tuning starts)"}
    _, got, info = start(path, "depth.metric=false")  # a relative run uses it whole
    assert_same(got, params)
    assert info["head"] == f"loaded from {path} (relative)"


def test_metric_named_state_dict_is_used_whole(released):
    paths, params = released
    cfg, got, info = start(paths[VKITTI])
    assert_same(got, params)
    assert info == {"backbone": f"loaded from {paths[VKITTI]} (encoder tiny)",
                    "head": f"loaded from {paths[VKITTI]} (metric, max_depth 80 m)"}
    _, got, info = start(paths[HYPERSIM])  # trained for 20 m, the run's depth.max_depth is 80
    assert_same(got, params)
    assert info["head"] == f"loaded from {paths[HYPERSIM]} (metric, max_depth 20 m)"
    assert info["max_depth"] == ("warning: the head was trained for max_depth 20 m; "
                                 "depth.max_depth=80 scales its output by 4")
    assert "max_depth" not in start(paths[HYPERSIM], "depth.max_depth=20")[2]
    _, got, info = start(paths[VKITTI], "depth.load_head=false")
    assert_same(got["depth_head"], random_depth(cfg)["depth_head"])
    assert info["head"] == "random init: depth.load_head=false"


def test_ambiguous_files_and_impossible_requests_are_refused(released, tmp_path):
    paths, params = released
    refusals = [
        ((paths[UNNAMED],), rf"{paths[UNNAMED]}: cannot tell whether its head is metric or "
                            r"relative .*set depth\.checkpoint_kind"),
        ((paths[RELATIVE], "depth.load_head=true"),
         rf"depth\.load_head=true: {paths[RELATIVE]} holds a relative head, depth\.metric=true "
         "trains a metric one"),
        ((paths[RELATIVE], "depth.load_head=maybe"),
         r"^depth\.load_head='maybe': choose one of auto, true, false$"),
        ((paths[RELATIVE], "depth.checkpoint_kind=metrc"),
         r"^depth\.checkpoint_kind='metrc': choose one of auto, metric, relative$"),
        ((tmp_path / "absent.pth",), f"no checkpoint at '{tmp_path / 'absent.pth'}'"),
    ]
    for args, message in refusals:
        with pytest.raises(RunError, match=message) as err:
            start(*args)
        assert "\n" not in str(err.value)
    _, got, info = start(paths[UNNAMED], "depth.checkpoint_kind=metric")  # stated: used whole
    assert_same(got, params)
    assert info["head"] == f"loaded from {paths[UNNAMED]} (metric, max_depth 80 m)"


def test_without_a_checkpoint_everything_is_random():
    cfg = get_config("tiny")
    params, info = init_depth(cfg)
    assert_same(params, random_depth(cfg))
    assert info == {"backbone": "random init (no depth.checkpoint)",
                    "head": "random init (no depth.checkpoint)"}
