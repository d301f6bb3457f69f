"""Config presets, one file each (big_vision style): ``irdepth_jax/configs/NAME.py`` defines
``get_config()`` returning an `irdepth_jax.config.Config`, built from the dataclasses of
`irdepth_jax.config_schema` (a preset never imports `irdepth_jax.config`, which loads it).

`irdepth_jax.config.get_config(NAME)` loads them, and ``--preset NAME`` of the CLI offers every
module found here, so a new preset is a new file. A file of this form also works as
``--config FILE`` of `irdepth train`.
"""

from __future__ import annotations

import pkgutil


def available() -> tuple[str, ...]:
    """The preset names: the modules of this package (not starting with '_'), sorted."""
    return tuple(sorted(m.name for m in pkgutil.iter_modules(__path__)
                        if not m.ispkg and not m.name.startswith("_")))
