import dataclasses
import importlib
import json
import pathlib
import typing

import pytest

from irdepth_jax.config import (
    Config,
    apply_overrides,
    available_presets,
    from_dict,
    get_config,
    to_dict,
)
from irdepth_jax.errors import ConfigError

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


def test_enumerations_are_checked_once_where_the_config_is_made():
    """A `Literal` field takes only its values: from an override, a replace, a config dict;
    the error names the key and every allowed value."""
    cfg = get_config("tiny")
    for override, message in (
            ("stage2.preprocessing=bogus", "stage2.preprocessing='bogus': choose one of hsv, value, "
                                           "rgb, blank, linear, he, clahe, plateau, double_plateau, "
                                           "dde, camera"),
            ("data.raw_bits=15", "data.raw_bits='15': choose one of 14, 16, auto"),
            ("depth.load_head=maybe", "depth.load_head='maybe': choose one of auto, true, false"),
            ("stage1.optimizer=sgd", "stage1.optimizer='sgd': choose one of adadelta, adamw"),
            ("stage1.i1_frames=some", "stage1.i1_frames='some': choose one of train, all")):
        with pytest.raises(ConfigError) as err:
            apply_overrides(cfg, [override])
        assert str(err.value) == message
    with pytest.raises(ConfigError, match=r"^stage2\.hue_mode='hsv': choose one of soft, argmax, "
                                          r"constant$"):
        dataclasses.replace(cfg, stage2=dataclasses.replace(cfg.stage2, hue_mode="hsv"))
    with pytest.raises(ConfigError, match=r"^unet\.use_rgg='no': expected true or false$"):
        dataclasses.replace(cfg, unet=dataclasses.replace(cfg.unet, use_rgg="no"))
    with pytest.raises(ConfigError, match=r"^stage1\.steps_i1=2\.5: expected an integer or none$"):
        from_dict({**to_dict(cfg), "stage1": {**to_dict(cfg)["stage1"], "steps_i1": 2.5}})
    got = apply_overrides(cfg, ["data.raw_bits=16", "depth.load_head=false", "stage1.steps_i1=none",
                                "stage1.learning_rate=2"])
    assert (got.data.raw_bits, got.depth.load_head, got.stage1.steps_i1) == (16, False, None)
    assert got.stage1.learning_rate == 2.0 and apply_overrides(cfg, ["data.raw_bits=auto"]
                                                               ).data.raw_bits == "auto"


def test_an_old_config_json_with_a_string_load_head_still_loads():
    """depth.load_head was "auto" | "true" | "false"; runs written then store the strings."""
    stored = to_dict(get_config("tiny"))
    for old, new in (("true", True), ("false", False), ("auto", "auto")):
        stored["depth"]["load_head"] = old
        assert from_dict(stored).depth.load_head == new
        assert type(from_dict(stored).depth.load_head) is type(new)


def test_the_library_lists_of_names_are_the_configs_literals():
    """One list per enumeration: the modules take theirs from the config's `Literal`s, or keep a
    registry (functions, sizes) whose names are exactly the `Literal`'s."""
    from irdepth_jax import config_schema as schema
    from irdepth_jax.config import STAGE1_IMAGES
    from irdepth_jax.data.source import PREPROCESSING
    from irdepth_jax.imaging.tonemap import TONEMAPS
    from irdepth_jax.models import depth_anything

    assert set(PREPROCESSING) == {*STAGE1_IMAGES, "rgb", "blank", *TONEMAPS}
    assert depth_anything.ENCODERS == typing.get_args(schema.Encoder)
    assert tuple(depth_anything._DTYPES) == typing.get_args(schema.ComputeDtype)
