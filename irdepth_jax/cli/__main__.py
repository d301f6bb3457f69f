"""`python -m irdepth_jax.cli`: the `irdepth` command."""

import sys

from irdepth_jax.cli import main

sys.exit(main())
