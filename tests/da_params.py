"""Random Depth Anything V2 params for tests, without compiling `init` (numpy draws on eval_shape)."""

import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from irdepth_jax.weights import expected_shapes


def random_params(cfg, seed: int = 0) -> dict:
    """Params of `DepthAnythingV2(cfg)`: kernels ~ N(0, 1/fan_in), norms and layer scales around
    1 and 0.5, biases and embeddings ~ N(0, 0.3^2), so that every path carries signal."""
    rng = np.random.default_rng(seed)
    flat = {}
    for path, shape in expected_shapes(cfg).items():
        leaf = path[-1]
        if leaf == "kernel":
            value = rng.normal(size=shape) / np.sqrt(np.prod(shape[:-1]))
        elif leaf == "scale":
            value = 1.0 + 0.2 * rng.normal(size=shape)
        elif leaf == "gamma":
            value = 0.5 + 0.2 * rng.normal(size=shape)
        else:
            value = 0.3 * rng.normal(size=shape)
        flat[path] = jnp.asarray(value, jnp.float32)
    return traverse_util.unflatten_dict(flat)
