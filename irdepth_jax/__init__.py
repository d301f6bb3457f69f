"""irdepth_jax: monocular depth from raw 14-bit thermal frames (MTSA-UNet -> HSV -> Depth Anything V2)."""

__version__ = "0.1.0"
