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
import typing
import warnings
from typing import Any

from irdepth_jax.config_schema import (
    Config,
    DataConfig,
    DepthConfig,
    Stage1Config,
    Stage2Config,
    UNetConfig,
    field_options,
    field_type,
)
from irdepth_jax.errors import ConfigError

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

RETYPED_VALUES: dict[str, dict[Any, Any]] = {
    "depth.load_head": {"true": True, "false": False},
}
"""Dotted config key -> {old value: its value now}, for the configs stored by runs and
checkpoints written before the key became typed (`upgrade_dict`)."""


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
    (`RENAMED_KEYS`) moved to the new ones and values of an old form (`RETYPED_VALUES`) in
    their new one; a `DeprecatedKeyWarning` for each when `where` (the
    file it came from) is given, silent otherwise (a config stored by an older version).

    Raises ConfigError when a key is given under both names.
    """
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in d.items()}
    for old, new in RENAMED_KEYS.items():
        (old_section, old_name), (new_section, new_name) = old.split("."), new.split(".")
        section = out.get(old_section)
        if not isinstance(section, dict) or old_name not in section:
            continue
        if new_name in out.get(new_section, {}):
            raise ConfigError(f"config key {old!r} is the old name of {new!r}; give only {new!r}")
        if where is not None:
            warnings.warn(f"{where}: config key {old!r} is deprecated, use {new!r} (same "
                          "meaning)", DeprecatedKeyWarning, stacklevel=2)
        out.setdefault(new_section, {})[new_name] = section.pop(old_name)
    for key, values in RETYPED_VALUES.items():
        section_name, name = key.split(".")
        section = out.get(section_name)
        if isinstance(section, dict) and isinstance(section.get(name), str):
            section[name] = values.get(section[name].lower(), section[name])
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

    Raises ConfigError listing the available presets for an unknown name.
    """
    import importlib

    names = available_presets()
    if preset not in names:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {list(names)}")
    cfg = importlib.import_module(f"irdepth_jax.configs.{preset}").get_config()
    if not isinstance(cfg, Config):
        raise TypeError(f"irdepth_jax/configs/{preset}.py: get_config() returned "
                        f"{type(cfg).__name__}, not a Config")
    return cfg


_TRUE_WORDS, _FALSE_WORDS = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def _parse_literal(text: str, literals: tuple) -> Any:
    """The value of `literals` (a `Literal` field's) that override text names, or `text` itself
    (which the config then refuses, listing the values)."""
    word = text.strip()
    for value in literals:
        if isinstance(value, bool):
            if word.lower() in (_TRUE_WORDS if value else _FALSE_WORDS):
                return value
        elif word == str(value):
            return value
    return word


def _parse_typed(text: str, key: str, kinds: tuple) -> Any:
    """Parses an override value to the first of the field's types `kinds` (e.g. (int,
    NoneType) for ``int | None``) that reads it; ConfigError naming the key when none does."""
    lowered = text.strip().lower()
    if lowered in ("none", "null") and type(None) in kinds:
        return None
    kind = next((k for k in kinds if k is not type(None)), str)
    or_none = " (or none)" if type(None) in kinds else ""
    if kind is bool:
        if lowered in _TRUE_WORDS or lowered in _FALSE_WORDS:
            return lowered in _TRUE_WORDS
        raise ConfigError(f"config key {key!r} expects true/false{or_none}, got {text!r}")
    if kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            what = "an integer" if kind is int else "a number"
            raise ConfigError(f"config key {key!r} expects {what}{or_none}, got {text!r}") from None
    if typing.get_origin(kind) is tuple:
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            raise ConfigError(f"config key {key!r} expects a tuple like (1, 2), got {text!r}") from None
        return tuple(value) if isinstance(value, (list, tuple)) else (value,)
    return text


def apply_overrides(cfg: Config, overrides: list[str] | tuple[str, ...]) -> Config:
    """Returns `cfg` with `section.key=value` (or top-level `key=value`) overrides applied.

    Raises ConfigError naming the key for an unknown key, a malformed item or a bad value
    (a value outside a `Literal` field's set: naming the values it allows).
    """
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form key=value")
        key, text = item.split("=", 1)
        key = current_key(key.strip(), f"override {item!r}")
        parts = key.split(".")
        if len(parts) == 1:
            cfg = _replace_field(cfg, parts[0], text, key)
        elif len(parts) == 2:
            section_name, field_name = parts
            section = _get_field(cfg, section_name, key)
            if not dataclasses.is_dataclass(section):
                raise ConfigError(f"unknown config key {key!r}")
            cfg = dataclasses.replace(
                cfg, **{section_name: _replace_field(section, field_name, text, key)}
            )
        else:
            raise ConfigError(f"unknown config key {key!r}")
    return cfg


def override_keys(overrides: list[str] | tuple[str, ...]) -> set[str]:
    """The dotted keys that `key=value` overrides set (old names as their new ones, silently)."""
    return {RENAMED_KEYS.get(k.strip(), k.strip())
            for k, _, _ in (item.partition("=") for item in overrides)}


def _get_field(obj: Any, name: str, key: str) -> Any:
    names = {f.name for f in dataclasses.fields(obj)}
    if name not in names:
        raise ConfigError(f"unknown config key {key!r}; known here: {', '.join(sorted(names))}")
    return getattr(obj, name)


def _replace_field(obj: Any, name: str, text: str, key: str) -> Any:
    if dataclasses.is_dataclass(_get_field(obj, name, key)):
        raise ConfigError(f"config key {key!r} is a section; set one of its fields")
    literals, kinds = field_options(field_type(type(obj), name))
    value = _parse_literal(text, literals) if literals else _parse_typed(text, key, kinds)
    return dataclasses.replace(obj, **{name: value})


def to_dict(cfg: Config) -> dict:
    """The config as plain JSON-able dicts (for logs and checkpoints)."""
    return dataclasses.asdict(cfg)


def from_dict(d: dict) -> Config:
    """Inverse of `to_dict`; keys of old names are mapped (`upgrade_dict`: a config stored by an
    older version; values of an old form too, `RETYPED_VALUES`), unknown keys or values that
    are not allowed raise ConfigError."""
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
                raise ConfigError(f"unknown config keys in {key!r}: {sorted(unknown)}")
            value = {k: tuple(v) if isinstance(v, list) else v for k, v in value.items()}
            kwargs[key] = cls(**value)
        elif key in {f.name for f in dataclasses.fields(Config)}:
            kwargs[key] = value
        else:
            raise ConfigError(f"unknown config key {key!r}")
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
        raise ConfigError(f"data.raw_bits {bits!r}: expected 14 or 16 ('auto' is resolved from "
                         "the training frames when a run starts)")
    return int(bits)
