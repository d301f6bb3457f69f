"""Pure array ops on thermal images: raw normalisation, GCM gradients, HSV colour, tone-mapping."""

import importlib

_EXPORTS = {
    "normalize_raw": "raw",
    "check_raw": "raw",
    "gradient_magnitude": "gradients",
    "resize_gradient": "gradients",
    "CLASS_HUES": "color",
    "class_hue": "color",
    "hsv_compose": "color",
    "hsv_to_rgb": "color",
}


def __getattr__(name):  # lazy, so `import irdepth_jax.imaging` stays cheap
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = sorted(_EXPORTS)
