import dataclasses
import importlib
import json
import pathlib

import pytest

from irdepth_jax.config import (
    Config,
    apply_overrides,
    available_presets,
    from_dict,
    get_config,
    to_dict,
)

PRESET_DICTS = pathlib.Path(__file__).parent / "data" / "preset_configs.json"
"""to_dict(get_config(name)) of each preset, as the code before presets became files made them."""


def test_paper_preset_has_paper_widths():
    cfg = get_config("paper")
    assert cfg.unet.widths == (32, 64, 128, 256)
    assert cfg.unet.bottleneck == 512
    assert cfg.unet.num_classes == 6
    assert cfg.stage1.w_seg == 1.0 and cfg.stage1.w_rec == 0.1
    assert cfg.stage2.learning_rate == 5e-6 and cfg.stage2.head_lr_multiplier == 10.0


def test_overrides_are_typed_and_strict():
    cfg = apply_overrides(
        get_config("tiny"),
        ["unet.use_rgg=false", "stage2.lambda_sky=0.25", "seed=3", "unet.widths=(2, 4, 4, 8)",
         "depth.checkpoint=/x.pth"],
    )
    assert cfg.unet.use_rgg is False
    assert cfg.stage2.lambda_sky == 0.25
    assert cfg.seed == 3
    assert cfg.unet.widths == (2, 4, 4, 8)
    assert cfg.depth.checkpoint == "/x.pth"
    with pytest.raises(ValueError, match="unet.nope"):
        apply_overrides(cfg, ["unet.nope=1"])
    with pytest.raises(ValueError, match="stage1.batch_size"):
        apply_overrides(cfg, ["stage1.batch_size=four"])
    with pytest.raises(ValueError, match="key=value"):
        apply_overrides(cfg, ["seed"])
    with pytest.raises(ValueError, match="preset"):
        get_config("huge")


def test_dict_round_trip():
    cfg = get_config("small")
    assert from_dict(to_dict(cfg)) == cfg
    with pytest.raises(ValueError):
        from_dict({**to_dict(cfg), "bogus": 1})


def test_configs_are_frozen():
    cfg = get_config("tiny")
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 1


def test_presets_are_the_configs_package():
    assert available_presets() == ("paper", "small", "tiny")
    with pytest.raises(ValueError, match=r"unknown preset 'huge'.*'paper', 'small', 'tiny'"):
        get_config("huge")
    for bad in ("", "__init__", "configs", "tiny.x", "irdepth_jax.config"):
        with pytest.raises(ValueError, match="unknown preset"):
            get_config(bad)


@pytest.mark.parametrize("name", ["paper", "small", "tiny"])
def test_presets_unchanged(name):
    """Every field, its value and its JSON type (1 vs 1.0, true vs 1) as before the move."""
    expected = json.loads(PRESET_DICTS.read_text())[name]
    cfg = get_config(name)
    assert isinstance(cfg, Config) and cfg.name == name
    got = json.dumps(to_dict(cfg), sort_keys=True, indent=1)
    assert got == json.dumps(expected, sort_keys=True, indent=1)
    assert from_dict(expected) == cfg
    assert get_config(name) is not cfg  # a fresh object each call


def test_every_preset_is_recorded():
    assert sorted(json.loads(PRESET_DICTS.read_text())) == list(available_presets())


@pytest.mark.parametrize("name", ["paper", "small", "tiny"])
def test_preset_docstring_names_its_command(name):
    module = importlib.import_module(f"irdepth_jax.configs.{name}")
    doc = module.get_config.__doc__ or ""
    assert f"--preset {name}" in doc
    assert {"tiny": "irdepth quickstart", "small": "python experiments/table",
            "paper": "irdepth train stage1"}[name] in doc
    assert "Time:" in doc and "docs/" in doc  # where its measured time is kept (not in the code)


def test_cli_preset_choices_come_from_the_package():
    from irdepth_jax.cli import build_parser

    parser = build_parser()
    for argv in (["train", "stage1", "--data", "d", "--workdir", "w"], ["quickstart"]):
        for name in available_presets():
            assert parser.parse_args([*argv, "--preset", name]).preset == name
        with pytest.raises(SystemExit):
            parser.parse_args([*argv, "--preset", "huge"])
