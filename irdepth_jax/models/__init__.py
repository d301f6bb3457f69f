"""Flax linen modules: MTSA-UNet (Stage I) and Depth Anything V2 (Stage II)."""

import importlib

_EXPORTS = {
    "MTSAUNet": "unet",
    "DepthAnythingV2": "depth_anything",
    "DepthAnythingConfig": "depth_anything",
    "depth_anything_config": "depth_anything",
}


def __getattr__(name):  # lazy, so importing one model does not import the others
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = sorted(_EXPORTS)
