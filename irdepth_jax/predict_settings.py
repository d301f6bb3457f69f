"""Defaults of `irdepth predict` (`irdepth_jax.predict`), in a module of their own that imports
nothing, so that the command line states them in its help without loading JAX."""

DEFAULT_BATCH = {"cpu": 1, "gpu": 8}
"""Frames per model call by backend. On a 2-core CPU batches are slower, not faster (`paper` UNet
+ ViT-S at 512x640: 0.38 frames/s at batch 1, 0.31 at batch 8, `experiments/bench_predict.py`:
the activations of 8 frames no longer fit the caches); a GPU needs batches to fill it."""
DEFAULT_FPS = 15.0
"""Frame rate of the depth videos (MS2's thermal camera records at 15 Hz)."""
