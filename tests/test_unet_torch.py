"""Parity of our MTSA-UNet with its PyTorch twin (experiments/unet_torch.py), the reference of
experiments/bench_unet.py: the same random weights give the same outputs (every head) in eval and
train mode, the same running statistics, the same gradients, and the same parameters after an SGD
or AdaDelta step of the benchmark's train steps on its Stage I loss.

Float32: outputs within 1e-5 in eval mode (measured <1e-6) and 1e-4 in train mode (measured
~1e-5: ~20 BatchNorms in series renormalise with batch statistics, and float32 ours and twin are
each that far from float64), parameters after one SGD step within 1e-5. The backward is checked
exactly with float64 networks (both sides, on ours' normalised input and RGG guides): 1e-9
(measured ~1e-13). In float32, a pre-activation within rounding of 0 can fall on different sides
of a ReLU in the two, which changes the gradient by O(1) there and by a few % in the layers
below (both are then valid subgradients, and ours or the twin's can be the one that differs from
float64), so a float32 gradient comparison cannot be tight.
"""

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

torch = pytest.importorskip("torch", reason="the PyTorch twin needs torch (the [torch] extra)")

from irdepth_experiments.bench_unet import (  # noqa: E402
    ADADELTA,
    make_torch_train_step,
    make_train_step,
    stage1_loss,
    stage1_loss_torch,
)
from irdepth_experiments.unet_torch import (  # noqa: E402
    MTSAUNetTorch,
    flax_to_torch_state,
    gradient_magnitude,
    load_flax_params,
)
from irdepth_jax.config import get_config  # noqa: E402
from irdepth_jax.imaging.raw import normalize_raw  # noqa: E402
from irdepth_jax.models.unet import MTSAUNet  # noqa: E402
from irdepth_jax.xla_cpu import conv, training_layers  # noqa: E402

pytestmark = pytest.mark.parity
TOL = 1e-5  # float32: max |ours - torch| <= TOL * max(1, max |torch|), per output / tensor
TRAIN_TOL = 1e-4  # float32, train mode (see above)
TOL64 = 1e-9  # float64 networks on the same inputs, relative to the tensor's largest value

TINY = get_config("tiny").unet  # widths 4-4-4-4, percentile input scaling, RGG
CASES = {
    "tiny": (TINY, (2, 32, 48)),
    # fixed scaling and a size that is no multiple of 16 (edge padding, cropped outputs)
    "tiny-fixed-27x45": (dataclasses.replace(TINY, raw_scale="fixed"), (2, 27, 45)),
    "tiny-no-rgg": (dataclasses.replace(TINY, use_rgg=False), (2, 32, 48)),
}
OUTPUTS = {"recon", "seg_logits", "saturation", "input_gradient"}


def _raw(shape, seed=0):
    """uint16 counts within 14 bits: a smooth scene (a few hundred counts of contrast) + noise."""
    rng = np.random.default_rng(seed)
    b, h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    scene = 7000 + 400 * np.sin(xx / 5.0 + yy / 7.0) + 300 * (xx > w // 2)
    counts = scene[None] + rng.normal(0, 40, (b, h, w)) + 500 * np.arange(b)[:, None, None]
    return np.clip(counts, 0, 2**14 - 1).astype(np.uint16)


def _image(raw, cfg):
    """Ours' input of `raw` (the twin normalises the counts itself): the pipeline's normalisation
    (`models.pipeline.unet_input`) of 14-bit counts."""
    return normalize_raw(jnp.asarray(raw), cfg.raw_scale, bits=14)


@functools.cache
def _random_variables(case, seed=0):
    """Random variables of ours (numpy; shared, not to be changed), every leaf random so that no
    term of the forward is trivially 0 or 1: kernels ~ N(0, 1 / fan_in) (lecun_normal, our
    init), BatchNorm scales 1 + N(0, 0.2^2), biases and running means N(0, 0.2^2), running
    variances U(0.5, 1.5). Drawn from the shapes (`jax.eval_shape`: nothing to compile)."""
    cfg, shape = CASES[case]
    shapes = jax.eval_shape(MTSAUNet(cfg).init, jax.random.key(0), jnp.zeros(shape, jnp.float32))
    rng = np.random.default_rng(seed)

    def draw(path, leaf):
        shape, name = leaf.shape, path[-1].key
        if name == "kernel":
            return rng.standard_normal(shape) / np.sqrt(np.prod(shape[:-1]))
        if name == "scale":
            return 1.0 + 0.2 * rng.standard_normal(shape)
        if name == "var":
            return rng.uniform(0.5, 1.5, shape)
        return 0.2 * rng.standard_normal(shape)  # bias, mean

    # float32, so that the float64 tests start both sides from the very same values
    return jax.tree_util.tree_map_with_path(lambda p, x: draw(p, x).astype(np.float32), shapes)


def _setup(case):
    cfg, shape = CASES[case]
    raw = _raw(shape)
    variables = _random_variables(case)
    return cfg, raw, variables, load_flax_params(MTSAUNetTorch(cfg), variables)


def _capture_inputs():
    """(seen, interceptor): under ``nn.intercept_methods(interceptor)``, an apply of ours records
    its normalised, padded input (seen['x']) and its RGG guides (seen['guide<height>'])."""
    seen = {}

    def interceptor(next_fun, args, kwargs, context):
        if context.method_name == "__call__" and context.module.name == "enc0":
            seen["x"] = args[0]
        if context.method_name == "__call__" and context.module.name == "rgg":
            seen[f"guide{args[2].shape[1]}"] = args[2]
        return next_fun(*args, **kwargs)

    return seen, interceptor


def _feed(twin, cfg, seen):
    """Makes `twin` take ours' input and RGG guides (`_capture_inputs`), so that a float64
    comparison is not limited by the float32 preprocessing in each (compared on its own, in
    float32, by test_forward_matches). XLA's rounding of the float32 guides differs by an ulp
    between programs (jit vs eager, or inside a different jitted function), so they are best
    captured from the very computation being compared."""
    x = torch.from_numpy(np.array(seen["x"])).permute(0, 3, 1, 2)
    guides = [None] * len(cfg.widths)
    if cfg.use_rgg:
        guides = [torch.from_numpy(np.array(seen[f"guide{x.shape[2] >> i}"])).permute(0, 3, 1, 2)
                  for i in range(len(cfg.widths))]
    twin.preprocess = lambda raw: (x, gradient_magnitude(x), guides)
    return twin


def _targets(cfg, raw):
    """Random reconstruction targets (B, H, W, 1) and labels (B, H, W) for the Stage I loss."""
    rng = np.random.default_rng(1)
    b, h, w = raw.shape
    target = rng.random((b, h, w, 1), dtype=np.float32)
    return target, rng.integers(0, cfg.num_classes, (b, h, w)).astype(np.int32)


def _torch_targets(target, labels, dtype=torch.float32):
    target = torch.from_numpy(np.ascontiguousarray(target.transpose(0, 3, 1, 2))).to(dtype)
    return target, torch.from_numpy(labels.astype(np.int64))


def _nhwc(t):
    return t.detach().permute(0, 2, 3, 1).numpy()


def _assert_close(ours, ref, what, tol=TOL):
    ours, ref = np.asarray(ours), np.asarray(ref)
    assert ours.shape == ref.shape, (what, ours.shape, ref.shape)
    err = float(np.abs(ours - ref).max())
    assert err <= tol * max(1.0, float(np.abs(ref).max())), f"{what}: max |ours - torch| = {err:.2e}"


def _assert_close_relative(ours, ref, what, tol=TOL64):
    ours, ref = np.asarray(ours), np.asarray(ref)
    assert ours.shape == ref.shape, (what, ours.shape, ref.shape)
    scale = float(np.abs(ref).max())
    assert scale > 0, f"{what}: all zero"
    err = float(np.abs(ours - ref).max())
    assert err <= tol * scale, f"{what}: max |ours - torch| / max |torch| = {err / scale:.2e}"


def test_parameter_count_and_names():
    cfg, raw, variables, twin = _setup("tiny")
    ours = sum(np.size(x) for x in jax.tree.leaves(variables["params"]))
    assert ours == sum(p.numel() for p in twin.parameters()) == 9436  # the tiny preset's "9.4k"
    for case in ("tiny-no-rgg",):
        cfg_, raw_, variables_, twin_ = _setup(case)
        assert sum(np.size(x) for x in jax.tree.leaves(variables_["params"])) == sum(
            p.numel() for p in twin_.parameters()
        )
    # every twin parameter and running statistic comes from one of ours, and back
    twin_state = {k for k in twin.state_dict() if not k.endswith("num_batches_tracked")}
    assert set(flax_to_torch_state(variables)) == twin_state
    with pytest.raises(ValueError, match="without a twin"):
        load_flax_params(MTSAUNetTorch(dataclasses.replace(cfg, use_rgg=False)), variables)


@pytest.mark.parametrize("train", [False, True], ids=["eval", "train"])
@pytest.mark.parametrize("case", list(CASES))
def test_forward_matches(case, train):
    cfg, raw, variables, twin = _setup(case)
    apply = jax.jit(lambda v, r: MTSAUNet(cfg).apply(v, r, train=train, mutable=["batch_stats"]))
    ours, updates = apply(variables, _image(raw, cfg))
    twin.train(train)
    with torch.no_grad():
        ref = twin(torch.from_numpy(raw))
    assert set(ours) == set(ref) == OUTPUTS
    tol = TRAIN_TOL if train else TOL
    for key in ours:
        _assert_close(ours[key], _nhwc(ref[key]), key, tol)
    if train:  # running averages updated alike (Flax's momentum and biased variance)
        expected = flax_to_torch_state({"batch_stats": updates["batch_stats"]})
        state = twin.state_dict()
        for key, value in expected.items():
            _assert_close(value, state[key], key, tol)
        assert not np.allclose(expected["bottleneck.bn1.running_var"],
                               flax_to_torch_state(variables)["bottleneck.bn1.running_var"])


@pytest.mark.parametrize("case", ["tiny", pytest.param("tiny-fixed-27x45", marks=pytest.mark.slow)])
# Winograd is `slow` (its compile is the file's longest); the default suite proves it in parts:
# the float64 Winograd kernel gradient = the direct sum to 1e-13 and the Conv layer taking it
# (test_fast_kernels: test_winograd_kernel_gradient_in_float64_and_where_it_is_taken,
# test_conv_matches_flax_conv[3x3_asym_winograd]), the UNet's direct gradients = the twin's (here)
@pytest.mark.parametrize("winograd", [False, pytest.param(True, marks=pytest.mark.slow)],
                         ids=["direct", "winograd"])
def test_float64_train_forward_and_gradients_match(case, winograd, monkeypatch):
    """Train mode with float64 networks, under the CPU training layers (`xla_cpu`): outputs,
    running statistics and every parameter's gradient of the benchmark's Stage I loss; with
    `winograd`, every 3x3 kernel gradient by Winograd (the `paper` preset's wide layers take it;
    `tiny`'s narrow ones would not)."""
    if winograd:
        monkeypatch.setattr(conv, "WINOGRAD_MIN_CHANNELS", 0)
    cfg, raw, variables, twin = _setup(case)
    target, labels = _targets(cfg, raw)
    model = MTSAUNet(cfg)

    def loss_fn(params, batch_stats, raw, target, labels):
        seen, interceptor = _capture_inputs()
        with training_layers(), nn.intercept_methods(interceptor):
            out, updates = model.apply(
                {"params": params, "batch_stats": batch_stats}, raw, train=True,
                mutable=["batch_stats"],
            )
        return stage1_loss(out, target, labels), (out, updates["batch_stats"], seen)

    with jax.enable_x64(True):
        v64 = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), variables)
        (loss, (out, batch_stats, seen)), grads = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(
            v64["params"], v64["batch_stats"], _image(raw, cfg), jnp.asarray(target, jnp.float64),
            jnp.asarray(labels),
        )
        assert out["recon"].dtype == grads["head_recon"]["kernel"].dtype == jnp.float64
        out, batch_stats, grads, seen = jax.device_get((out, batch_stats, grads, seen))
    _feed(twin, cfg, seen)
    twin = twin.double().train()
    ref = twin(torch.from_numpy(raw))
    ref_loss = stage1_loss_torch(ref, *_torch_targets(target, labels, torch.float64))
    ref_loss.backward()
    assert abs(float(loss) - ref_loss.item()) <= TOL64 * ref_loss.item()
    for key in OUTPUTS:
        _assert_close_relative(out[key], _nhwc(ref[key]), key)
    state = twin.state_dict()
    for key, value in flax_to_torch_state({"batch_stats": batch_stats}, torch.float64).items():
        _assert_close_relative(value, state[key], key)
    # flax_to_torch_state lays our gradients out as the twin's parameters
    for key, value in flax_to_torch_state({"params": grads}, torch.float64).items():
        _assert_close_relative(value, twin.get_parameter(key).grad, f"d loss / d {key}")


def _train_steps(case, tx, torch_optimizer, steps, float64=False):
    """(ours, twin's) state dicts after `steps` calls of the benchmark's two train steps, and the
    state before (float64: the network in float64 in both, from the same float32 weights)."""
    cfg, raw, variables, twin = _setup(case)
    target, labels = _targets(cfg, raw)
    dtype = torch.float64 if float64 else torch.float32
    args = (torch.from_numpy(raw), *_torch_targets(target, labels, dtype))
    torch_step = make_torch_train_step(twin.to(dtype), torch_optimizer(twin.parameters()))
    with jax.enable_x64(float64):
        cast = jnp.float64 if float64 else jnp.float32
        cast_variables = jax.tree.map(lambda x: jnp.asarray(x, cast), variables)
        params, batch_stats = cast_variables["params"], cast_variables["batch_stats"]
        if float64:  # ours' inputs from the forward of a jitted train step
            def forward(variables, raw):
                seen, interceptor = _capture_inputs()
                with nn.intercept_methods(interceptor):
                    MTSAUNet(cfg).apply(variables, raw, train=True, mutable=["batch_stats"])
                return seen

            _feed(twin, cfg, jax.device_get(jax.jit(forward)(cast_variables, _image(raw, cfg))))
        step = make_train_step(MTSAUNet(cfg), tx)
        opt_state = tx.init(params)
        for _ in range(steps):
            params, batch_stats, opt_state, loss = step(
                params, batch_stats, opt_state, _image(raw, cfg), jnp.asarray(target, cast),
                jnp.asarray(labels),
            )
            torch_loss = torch_step(*args).item()
            assert abs(float(loss) - torch_loss) <= TOL * torch_loss
        ours = flax_to_torch_state({"params": params, "batch_stats": batch_stats}, dtype)
    return ours, twin.state_dict(), flax_to_torch_state(variables, dtype)


def test_sgd_step_matches():
    """One SGD step of the benchmark's train steps (float32): the same parameters and running
    statistics after it to 1e-5, and the same step per tensor to 10 % of its largest entry (plus
    the parameters' rounding; a float32 gradient differs by up to a few % where a ReLU flips, see
    above, and a wrong or missing term of the backward gives O(1)). The exact check is the float64
    gradient test."""
    lr = 0.01  # parameter steps up to ~1e-2
    ours, ref, before = _train_steps("tiny", optax.sgd(lr), lambda p: torch.optim.SGD(p, lr=lr), 1)
    for key, value in ours.items():
        _assert_close(value, ref[key], key)
        step, ref_step = (value - before[key]).numpy(), (ref[key] - before[key]).numpy()
        assert np.abs(ref_step).max() > 1e-7, f"{key}: did not move"
        rounding = 4 * np.spacing(np.abs(before[key].numpy()).max())  # of the parameters themselves
        err = np.abs(step - ref_step).max()
        assert err <= 0.1 * np.abs(ref_step).max() + rounding, f"{key} step: max |diff| {err:.1e}"


@pytest.mark.slow  # 25 s on 2 cores; the SGD step above checks the same train steps' update
def test_adadelta_steps_match():
    """The benchmark's two AdaDelta train steps (optax.adadelta and torch.optim.Adadelta with
    `ADADELTA`), 2 steps (the second uses both running averages), in float64: AdaDelta's update
    (at most sqrt(eps / (1 - rho)) ~ 3e-3 per step) is compared to its own size."""
    rate = dict(ADADELTA)
    lr = rate.pop("learning_rate")
    ours, ref, before = _train_steps(
        "tiny", optax.adadelta(lr, **rate), lambda p: torch.optim.Adadelta(p, lr=lr, **rate), 2,
        float64=True,
    )
    tol = 1e-6  # the guides, captured from another jitted function, may differ by an ulp
    for key, value in ours.items():
        if key.endswith(("weight", "bias")):
            _assert_close_relative(value - before[key], ref[key] - before[key], f"{key} update", tol)
        else:
            _assert_close_relative(value, ref[key], key, tol)
