"""The native kernel gradient (`irdepth_jax.xla_cpu.native_conv`, a C++ XLA FFI custom call,
opt-in) against a float64 numpy sum worked from the definition, and against autodiff of
`lax.conv_general_dilated`; where `conv.kernel_gradient` takes it; that a default run never
builds it, that asking for it where it cannot build is refused, and that concurrent builds do
not share a temporary file.

The kernel tiles input channels by up to 12 (AVX-512; 6 elsewhere) and output channels by 32
(16), so the cases use input channel counts that leave remainders (1, 13, 40) and one and two
output tiles, odd image sizes, asymmetric paddings and paddings wider than the kernel.
"""

import functools
import os
import subprocess
import sys
import threading

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from irdepth_jax.xla_cpu import NATIVE_ENV, conv, layers, native_conv

NHWC = ("NHWC", "HWIO", "NHWC")

needs_native = pytest.mark.skipif(
    not native_conv.available(),
    reason="the native kernel could not be built here (no C++ compiler)")


def kernel_gradient_by_definition(x, g, kernel_size, pads):
    """float64 numpy: dw[p, q, c, d] = sum_{b,i,j} x_pad[b, i + p, j + q, c] g[b, i, j, d]."""
    x, g = np.asarray(x, np.float64), np.asarray(g, np.float64)
    (top, bottom), (left, right) = pads
    x_pad = np.pad(x, ((0, 0), (top, bottom), (left, right), (0, 0)))
    kh, kw = kernel_size
    out_h, out_w = g.shape[1:3]
    return np.stack([np.stack([np.einsum("bhwc,bhwd->cd", x_pad[:, p:p + out_h, q:q + out_w], g)
                               for q in range(kw)]) for p in range(kh)])


def case(batch, height, width, c_in, c_out, kernel_size, pads, seed=0):
    kh, kw = kernel_size
    out_h = height + sum(pads[0]) - kh + 1
    out_w = width + sum(pads[1]) - kw + 1
    rng = np.random.default_rng(seed)
    return (jnp.asarray(rng.standard_normal((batch, height, width, c_in)), jnp.float32),
            jnp.asarray(rng.standard_normal((batch, out_h, out_w, c_out)), jnp.float32))


@needs_native
@pytest.mark.parametrize("kernel_size, pads", [
    ((3, 3), ((1, 1), (1, 1))), ((3, 3), ((2, 0), (0, 1))), ((3, 2), ((2, 0), (0, 1))),
    ((5, 5), ((2, 1), (0, 3))), ((3, 3), ((3, 0), (1, 4))), ((1, 1), ((0, 0), (0, 0)))])
@pytest.mark.parametrize("c_in", [1, 13, 40])
def test_native_kernel_gradient_matches_the_definition(kernel_size, pads, c_in):
    tile = native_conv.tile_channels()
    for c_out in (tile, 2 * tile):
        x, g = case(2, 11, 9, c_in, c_out, kernel_size, pads)
        got = jax.jit(native_conv.kernel_gradient_native, static_argnums=(2, 3))(x, g, kernel_size, pads)
        want = kernel_gradient_by_definition(x, g, kernel_size, pads)
        assert got.shape == want.shape and got.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=2e-6 * np.abs(want).max(),
                                   err_msg=f"c_out={c_out}")


@needs_native
def test_native_kernel_gradient_is_deterministic_and_matches_autodiff_on_a_large_layer():
    """Several rows of tiles shared among the intra-op threads: the same bits on every call,
    and XLA's own kernel gradient to float32 rounding."""
    pads = ((1, 1), (1, 1))
    x, g = case(2, 40, 56, 64, 64, (3, 3), pads, seed=1)
    native = jax.jit(native_conv.kernel_gradient_native, static_argnums=(2, 3))
    first = np.asarray(native(x, g, (3, 3), pads))
    for _ in range(3):
        np.testing.assert_array_equal(np.asarray(native(x, g, (3, 3), pads)), first)
    kernel = jnp.zeros((3, 3, 64, 64))
    want = jax.jit(lambda g: jax.vjp(lambda k: lax.conv_general_dilated(
        x, k, (1, 1), pads, dimension_numbers=NHWC), kernel)[1](g)[0])(g)
    np.testing.assert_allclose(first, np.asarray(want), rtol=0, atol=1e-5 * float(jnp.abs(want).max()))


@needs_native
def test_where_the_kernel_gradient_takes_the_native_kernel():
    method, tile = functools.partial(conv.kernel_gradient_method, native=True), native_conv.tile_channels()
    assert method((4, 256, 320, 64), (4, 256, 320, 32), (3, 3)) == "native"  # the UNet's full-resolution layers
    assert method((4, 128, 160, 128), (4, 128, 160, 64), (3, 3)) == "native"
    assert method((4, 256, 320, 1), (4, 256, 320, 32), (3, 3)) == "native"  # the 1-channel input layer
    assert method((4, 64, 80, 128), (4, 64, 80, 128), (3, 3)) == "winograd"  # wide: fewer multiply-adds
    assert method((4, 256, 320, 64), (4, 256, 320, tile + 1), (3, 3)) != "native"  # not whole tiles
    assert method((4, 256, 320, 64), (4, 256, 320, 32), (3, 3), jnp.float64) != "native"
    assert method((4, 256, 320, 64), (4, 256, 320, 32), (3, 3), jnp.bfloat16) != "native"
    method = conv.kernel_gradient_method  # without the native kernel: the XLA ways
    assert method((4, 256, 320, 64), (4, 256, 320, 32), (3, 3)) == "row_blocks"
    assert method((4, 128, 160, 128), (4, 128, 160, 64), (3, 3)) == "winograd"


@needs_native
@pytest.mark.parametrize("kernel_size", [(3, 3), (1, 1)])
def test_conv_module_with_the_native_kernel_matches_flax(kernel_size):
    """`flax.linen.Conv`'s parameter gradient under the CPU layers with the native kernel (3x3 and
    the 1x1 einsum's backward on images) against its plain autodiff; the jaxpr has the custom
    call."""
    features = native_conv.tile_channels()
    x = jnp.asarray(np.random.default_rng(2).standard_normal((2, 13, 10, 7)), jnp.float32)
    module = nn.Conv(features, kernel_size, padding="SAME")
    params = module.init(jax.random.key(0), x)
    w = jnp.asarray(np.random.default_rng(3).standard_normal((2, 13, 10, features)), jnp.float32)
    loss = jax.grad(lambda p, x: jnp.sum(w * module.apply(p, x)), (0, 1))

    def native_loss(p, x):
        with nn.intercept_methods(functools.partial(layers.intercept, native=True)):
            return loss(p, x)

    for got, want in zip(jax.tree.leaves(jax.jit(native_loss)(params, x)), jax.tree.leaves(jax.jit(loss)(params, x))):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0,
                                   atol=2e-6 * float(jnp.abs(want).max()))
    assert native_conv.TARGET in str(jax.make_jaxpr(native_loss)(params, x))


def _in_subprocess(code: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "JAX_PLATFORMS": "cpu", **env})


@needs_native
def test_a_fresh_machine_builds_the_kernel_into_its_cache(tmp_path):
    """An empty cache (a user's first run): the kernel is compiled there and gives the same
    bits as the build this process loaded."""
    pads = ((1, 1), (1, 1))
    x, g = case(1, 6, 5, 3, native_conv.tile_channels(), (3, 3), pads)
    np.save(tmp_path / "x.npy", np.asarray(x))
    np.save(tmp_path / "g.npy", np.asarray(g))
    code = ("import numpy as np, jax\n"
            "from irdepth_jax.xla_cpu import native_conv\n"
            f"x, g = np.load({str(tmp_path / 'x.npy')!r}), np.load({str(tmp_path / 'g.npy')!r})\n"
            f"np.save({str(tmp_path / 'dw.npy')!r}, np.asarray(jax.jit(native_conv.kernel_gradient_native, "
            f"static_argnums=(2, 3))(x, g, (3, 3), {pads!r})))")
    built = _in_subprocess(code, XDG_CACHE_HOME=str(tmp_path / "cache"))
    assert built.returncode == 0, built.stderr
    assert len(list((tmp_path / "cache" / "irdepth_jax" / "native").glob("native_conv_*.so"))) == 1
    here = jax.jit(native_conv.kernel_gradient_native, static_argnums=(2, 3))(x, g, (3, 3), pads)
    np.testing.assert_array_equal(np.load(tmp_path / "dw.npy"), np.asarray(here))


TRAIN_A_CONV = (
    "import jax, jax.numpy as jnp, flax.linen as nn\n"
    "from irdepth_jax.errors import RunError\n"
    "from irdepth_jax.xla_cpu import native_conv, training_layers\n"
    "x = jnp.ones((2, 16, 16, 8)); m = nn.Conv(32, (3, 3)); p = m.init(jax.random.key(0), x)\n"
    "def grads(p):\n"
    "    with training_layers():\n"
    "        return jax.grad(lambda p: jnp.sum(m.apply(p, x) ** 2))(p)\n"
    "try:\n"
    "    text = jax.jit(grads).lower(p).as_text()\n"
    "except RunError as e:\n"
    "    print('refused:', e)\n"
    "else:\n"
    "    print(native_conv.TARGET in text, native_conv._loaded.cache_info().currsize)\n")


def test_a_default_run_never_builds_or_loads_the_kernel(tmp_path):
    """Unset (or 0): the XLA ways, and the build is not even tried (an empty cache stays empty)."""
    for value in (None, "0"):
        env = {k: v for k, v in os.environ.items() if k != NATIVE_ENV}
        if value is not None:
            env[NATIVE_ENV] = value
        done = subprocess.run([sys.executable, "-c", TRAIN_A_CONV], capture_output=True, text=True, timeout=300,
                              env={**env, "JAX_PLATFORMS": "cpu", "XDG_CACHE_HOME": str(tmp_path)})
        assert done.returncode == 0, done.stderr
        assert done.stdout.split() == ["False", "0"], value
    assert not list(tmp_path.rglob("*"))


def test_asked_for_but_unbuildable_is_refused_with_the_reason(tmp_path):
    failing = _in_subprocess(TRAIN_A_CONV, CXX="false", XDG_CACHE_HOME=str(tmp_path), **{NATIVE_ENV: "1"})
    assert failing.returncode == 0, failing.stderr
    assert failing.stdout.startswith(f"refused: {NATIVE_ENV}=1: the native convolution kernel is not available: "
                                     "the build or load failed: false ")
    assert not list(tmp_path.rglob("*.so")) and not list(tmp_path.rglob("*.tmp"))


def test_concurrent_builds_write_temporary_files_of_their_own(tmp_path, monkeypatch):
    """Two threads of one process building at once (same pid) compile to different temporary
    files and each renames its own into place."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    outputs, both_started = [], threading.Barrier(2)

    def fake_compiler(command, **kwargs):
        if "--version" in command:
            return subprocess.CompletedProcess(command, 0, "fake 1.0", "")
        output = command[command.index("-o") + 1]
        outputs.append(output)
        both_started.wait(timeout=30)  # the second build starts before the first one finishes
        with open(output, "w") as f:
            f.write(output)
        return subprocess.CompletedProcess(command, 0, "", "")

    monkeypatch.setattr(native_conv.subprocess, "run", fake_compiler)
    results, errors = [], []

    def build():
        try:
            results.append(native_conv._build("c++"))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=build) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert errors == [] and len(results) == 2 and results[0] == results[1]
    assert len(set(outputs)) == 2
    assert results[0].read_text() in outputs  # one whole build in place, no leftovers
    assert [p.name for p in results[0].parent.iterdir()] == [results[0].name]


def test_calling_the_native_kernel_without_it_says_why(monkeypatch):
    monkeypatch.setattr(native_conv, "available", lambda: False)
    x, g = case(1, 4, 4, 2, 32, (3, 3), ((1, 1), (1, 1)))
    with pytest.raises(RuntimeError, match="not available"):
        native_conv.kernel_gradient_native(x, g, (3, 3), ((1, 1), (1, 1)))


@needs_native
def test_the_kernels_flops_are_counted_as_xla_counts_the_matmuls_they_replace():
    """XLA's cost analysis counts a custom call as no FLOPs; `flops_in` adds 2 x kh*kw*C_in*C_out x
    B*H'*W' per call, so the benchmarks' GFLOP/s keep counting the same arithmetic."""
    x, k = jnp.ones((2, 16, 20, 8)), jnp.ones((3, 3, 8, 32))

    def loss(x, k, native=True):
        return jnp.sum(conv.conv_general_dilated(x, k, (1, 1), ((1, 1), (1, 1)), dimension_numbers=NHWC,
                                                 native=native) ** 2)

    text = jax.jit(jax.grad(loss, 1)).lower(x, k).compile().as_text()
    assert native_conv.flops_in(text) == 2 * 9 * 8 * 32 * (2 * 16 * 20)
    xla_ways = jax.jit(jax.grad(functools.partial(loss, native=False), 1)).lower(x, k).compile().as_text()
    assert native_conv.flops_in(xla_ways) == 0
