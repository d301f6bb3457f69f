"""Configuration: frozen dataclasses, and `get_config` for the presets in `irdepth_jax/configs/`.

Every hyper-parameter, ablation switch and path the library uses lives here, so that each
ablation of the paper is a `key=value` override (see `apply_overrides`):

    cfg = get_config("tiny")
    cfg = apply_overrides(cfg, ["unet.use_rgg=false", "stage2.sky_loss=false"])

Presets are files, one each, `irdepth_jax/configs/NAME.py` defining `get_config()` (its
docstring says what the preset is for, the command that uses it and how long it takes):
  * `paper`: the paper's MTSA-UNet widths (32, 64, 128, 256, bottleneck 512, 6 classes),
    Depth Anything V2 `vits`, 50 epochs per stage, the paper's batch sizes; meant for a GPU.
  * `small`: an 8-16-32-64 UNet and a small ViT; minutes on a CPU, used for the committed
    synthetic-benchmark results.
  * `tiny`: a 9.4k-parameter UNet and a 4-block ViT; seconds on a CPU, used by the tests and
    the quickstart.

Renamed keys (`RENAMED_KEYS`) still work under their old names: in overrides and config files
with a `DeprecatedKeyWarning` naming the new key, and silently in the configs stored by runs
and checkpoints written before the rename (`from_dict`).
"""

from __future__ import annotations

import ast
import dataclasses
import re
import warnings
from typing import Any

from irdepth_jax.config_schema import (
    Config,
    DataConfig,
    DepthConfig,
    Stage1Config,
    Stage2Config,
    UNetConfig,
)

CLASS_NAMES: tuple[str, ...] = ("sky", "building", "car", "bicycle", "road", "tree")
"""Semantic classes of the paper, in label order (label 255 = unlabelled)."""
MS2_DEPTH_LABELS: dict[str, str] = {
    "depth_filtered": "proj_depth", "depth": "proj_depth", "depth_multi": "proj_depth",
    "depth_gt": "sync_data", "depth_refl_gt": "sync_data"}
"""MS2's depth label versions (<folder>/<seq>/thr/<name>/, uint16 metres x 256) by name, with
the folder holding them (`data.ms2`; `irdepth eval --gt`); published numbers differ by about
0.04 AbsRel between versions. 'depth_filtered' is the default (the official loader's)."""
IGNORE_LABEL = 255
SKY_CLASS = 0
STAGE1_IMAGES: tuple[str, ...] = ("hsv", "value")
"""Stage II inputs the Stage I model makes (`stage2.preprocessing`): 'hsv', its pseudo-RGB, and
'value', its V channel alone as a grey image (the attribution arm of table 1: what H and S add).
The other inputs are made on the host (`data.source.host_image`)."""


RENAMED_KEYS: dict[str, str] = {
    "stage1.stage12_learning_rate": "stage1.i2_learning_rate",
}
"""Old dotted config key -> its new name."""


class DeprecatedKeyWarning(FutureWarning):
    """A config key was given under its old name (`RENAMED_KEYS`); it is used as the new one."""


def current_key(key: str, where: str = "override") -> str:
    """The name of a dotted config key now: `key` itself, or for an old name its new one, with a
    `DeprecatedKeyWarning` naming both (and `where` it was given)."""
    new = RENAMED_KEYS.get(key.strip())
    if new is None:
        return key
    warnings.warn(f"{where}: config key {key.strip()!r} is deprecated, use {new!r} (same meaning)",
                  DeprecatedKeyWarning, stacklevel=3)
    return new


def upgrade_dict(d: dict, where: str | None = None) -> dict:
    """A nested config dict (`to_dict`'s form, possibly partial) with the keys of old names
    (`RENAMED_KEYS`) moved to the new ones; a `DeprecatedKeyWarning` for each when `where` (the
    file it came from) is given, silent otherwise (a config stored by an older version).

    Raises ValueError when a key is given under both names.
    """
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in d.items()}
    for old, new in RENAMED_KEYS.items():
        (old_section, old_name), (new_section, new_name) = old.split("."), new.split(".")
        section = out.get(old_section)
        if not isinstance(section, dict) or old_name not in section:
            continue
        if new_name in out.get(new_section, {}):
            raise ValueError(f"config key {old!r} is the old name of {new!r}; give only {new!r}")
        if where is not None:
            warnings.warn(f"{where}: config key {old!r} is deprecated, use {new!r} (same "
                          "meaning)", DeprecatedKeyWarning, stacklevel=2)
        out.setdefault(new_section, {})[new_name] = section.pop(old_name)
    return out


def renamed_hint(text: str) -> str:
    """'' or, when `text` (an error message) names an old config field, the sentence that says
    its new key (for errors the keys cannot be mapped in, e.g. a dataclass keyword of a .py
    config file)."""
    hints = [f"{old!r} is now {new!r}" for old, new in RENAMED_KEYS.items()
             if re.search(rf"\b{re.escape(old.split('.')[-1])}\b", text)]
    return f" (renamed config key: {'; '.join(hints)})" if hints else ""


def available_presets() -> tuple[str, ...]:
    """The preset names, sorted: the modules of the `irdepth_jax.configs` package."""
    from irdepth_jax import configs

    return configs.available()


def get_config(preset: str = "paper") -> Config:
    """Returns a fresh `Config` for a preset name: `irdepth_jax.configs.<preset>.get_config()`.

    Raises ValueError listing the available presets for an unknown name.
    """
    import importlib

    names = available_presets()
    if preset not in names:
        raise ValueError(f"unknown preset {preset!r}; choose one of {list(names)}")
    cfg = importlib.import_module(f"irdepth_jax.configs.{preset}").get_config()
    if not isinstance(cfg, Config):
        raise TypeError(f"irdepth_jax/configs/{preset}.py: get_config() returned "
                        f"{type(cfg).__name__}, not a Config")
    return cfg


_TYPE_EXAMPLES = {"bool": False, "int": 0, "float": 0.0, "str": ""}
"""A value of each annotated type, standing in for an optional field's current None."""


def _parse_value(text: str, current: Any, key: str, types: tuple[str, ...] = ()) -> Any:
    """Parses an override value to the type of the field it replaces: the type of its current
    value, or, while that is None, the first type of its annotation `types` (e.g. ('int',
    'None') for ``int | None``)."""
    lowered = text.strip().lower()
    if lowered in ("none", "null"):
        return None
    if current is None:
        current = next((_TYPE_EXAMPLES[t] for t in types if t in _TYPE_EXAMPLES), None)
    or_none = " (or none)" if "None" in types else ""
    if isinstance(current, bool):
        if lowered in ("1", "true", "yes", "on"):
            return True
        if lowered in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"config key {key!r} expects true/false{or_none}, got {text!r}")
    if isinstance(current, int) and not isinstance(current, bool):
        try:
            return int(text)
        except ValueError:
            raise ValueError(f"config key {key!r} expects an integer{or_none}, got {text!r}"
                             ) from None
    if isinstance(current, float):
        try:
            return float(text)
        except ValueError:
            raise ValueError(f"config key {key!r} expects a number{or_none}, got {text!r}"
                             ) from None
    if isinstance(current, tuple):
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            raise ValueError(f"config key {key!r} expects a tuple like (1, 2), got {text!r}") from None
        return tuple(value) if isinstance(value, (list, tuple)) else (value,)
    if current is None:  # optional field: guess from the text
        try:
            return ast.literal_eval(text)
        except (ValueError, SyntaxError):
            return text
    return text


def apply_overrides(cfg: Config, overrides: list[str] | tuple[str, ...]) -> Config:
    """Returns `cfg` with `section.key=value` (or top-level `key=value`) overrides applied.

    Raises ValueError naming the key for an unknown key, a malformed item or a bad value.
    """
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override {item!r} is not of the form key=value")
        key, text = item.split("=", 1)
        key = current_key(key.strip(), f"override {item!r}")
        parts = key.split(".")
        if len(parts) == 1:
            cfg = _replace_field(cfg, parts[0], text, key)
        elif len(parts) == 2:
            section_name, field_name = parts
            section = _get_field(cfg, section_name, key)
            if not dataclasses.is_dataclass(section):
                raise ValueError(f"unknown config key {key!r}")
            cfg = dataclasses.replace(
                cfg, **{section_name: _replace_field(section, field_name, text, key)}
            )
        else:
            raise ValueError(f"unknown config key {key!r}")
    return cfg


def override_keys(overrides: list[str] | tuple[str, ...]) -> set[str]:
    """The dotted keys that `key=value` overrides set (old names as their new ones, silently)."""
    return {RENAMED_KEYS.get(k.strip(), k.strip())
            for k, _, _ in (item.partition("=") for item in overrides)}


def _get_field(obj: Any, name: str, key: str) -> Any:
    names = {f.name for f in dataclasses.fields(obj)}
    if name not in names:
        raise ValueError(f"unknown config key {key!r}; known here: {', '.join(sorted(names))}")
    return getattr(obj, name)


def _replace_field(obj: Any, name: str, text: str, key: str) -> Any:
    current = _get_field(obj, name, key)
    if dataclasses.is_dataclass(current):
        raise ValueError(f"config key {key!r} is a section; set one of its fields")
    types = str({f.name: f.type for f in dataclasses.fields(obj)}[name]).split(" | ")
    try:
        value = _parse_value(text, current, key, tuple(types))
    except ValueError:
        # a field annotated `int | str` (e.g. data.raw_bits = 14 | 16 | 'auto') takes words too
        if "str" not in types:
            raise
        value = text.strip()
    if value is None and "None" not in types:  # 'none' is a word for a plain str field
        value = text.strip()
    return dataclasses.replace(obj, **{name: value})


def to_dict(cfg: Config) -> dict:
    """The config as plain JSON-able dicts (for logs and checkpoints)."""
    return dataclasses.asdict(cfg)


def from_dict(d: dict) -> Config:
    """Inverse of `to_dict`; keys of old names are mapped (`upgrade_dict`: a config stored by an
    older version), unknown keys raise ValueError."""
    d = upgrade_dict(d)
    sections = {
        "unet": UNetConfig,
        "depth": DepthConfig,
        "data": DataConfig,
        "stage1": Stage1Config,
        "stage2": Stage2Config,
    }
    kwargs = {}
    for key, value in d.items():
        if key in sections:
            cls = sections[key]
            known = {f.name: f for f in dataclasses.fields(cls)}
            unknown = set(value) - set(known)
            if unknown:
                raise ValueError(f"unknown config keys in {key!r}: {sorted(unknown)}")
            value = {k: tuple(v) if isinstance(v, list) else v for k, v in value.items()}
            kwargs[key] = cls(**value)
        elif key in {f.name for f in dataclasses.fields(Config)}:
            kwargs[key] = value
        else:
            raise ValueError(f"unknown config key {key!r}")
    return Config(**kwargs)


STAGE1_MODEL_KEYS: tuple[str, ...] = (
    *(f"unet.{f.name}" for f in dataclasses.fields(UNetConfig)), "data.raw_bits")
"""The dotted keys that define a Stage I model: its variables' shapes (widths, classes, RGG) and
what it computes from the raw counts (normalisation, bit depth). A Stage II run takes them from
its Stage I checkpoint."""


def get_key(cfg: Config, key: str) -> Any:
    """The value of a dotted config key (``section.field`` or a top-level field)."""
    value: Any = cfg
    for part in key.split("."):
        value = getattr(value, part)
    return value


def with_keys(cfg: Config, values: dict[str, Any]) -> Config:
    """`cfg` with the dotted keys of `values` (``section.field`` or top-level) set to them."""
    for key, value in values.items():
        section, _, name = key.rpartition(".")
        if not section:
            cfg = dataclasses.replace(cfg, **{name: value})
        else:
            cfg = dataclasses.replace(cfg, **{section: dataclasses.replace(
                getattr(cfg, section), **{name: value})})
    return cfg


def resolved_raw_bits(cfg: Config) -> int:
    """`cfg.data.raw_bits` as 14 or 16; 'auto' must have been resolved from the data first."""
    bits = cfg.data.raw_bits
    if bits not in (14, 16):
        raise ValueError(f"data.raw_bits {bits!r}: expected 14 or 16 ('auto' is resolved from "
                         "the training frames when a run starts)")
    return int(bits)
