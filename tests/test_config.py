import dataclasses

import pytest

from irdepth_jax.config import apply_overrides, from_dict, get_config, to_dict


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
