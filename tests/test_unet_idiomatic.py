"""The benchmarks' PyTorch opponent (experiments/unet_idiomatic.py) computes what ours computes:
with our parameter tensors, the same outputs in eval and train mode and the same Stage I loss
(float32 tolerances of tests/test_unet_torch.py), while it carries none of the parity twin's
extra operations (fewer torch operator calls per train step)."""

import jax
import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the PyTorch opponent needs torch (the [torch] extra)")

from test_unet_torch import CASES, TOL, TRAIN_TOL, _assert_close, _image, _nhwc, _random_variables, _raw  # noqa: E402

from irdepth_experiments.bench_unet import (  # noqa: E402
    ADADELTA,
    make_torch_train_step,
    stage1_loss,
    stage1_loss_torch,
)
from irdepth_experiments.unet_idiomatic import MTSAUNetIdiomatic  # noqa: E402
from irdepth_experiments.unet_torch import MTSAUNetTorch, load_flax_params  # noqa: E402
from irdepth_jax.models.unet import MTSAUNet  # noqa: E402

pytestmark = pytest.mark.parity


def _targets(cfg, shape):
    rng = np.random.default_rng(1)
    b, h, w = shape
    return (rng.random((b, h, w, 1), dtype=np.float32),
            rng.integers(0, cfg.num_classes, (b, h, w)).astype(np.int32))


@pytest.mark.parametrize("train", [False, True], ids=["eval", "train"])
@pytest.mark.parametrize("case", ["tiny", "tiny-fixed-27x45"])
def test_outputs_and_loss_match_ours(case, train):
    cfg, shape = CASES[case]
    raw, variables = _raw(shape), _random_variables(case)
    target, labels = _targets(cfg, shape)

    def ours_fn(v, r):
        out, _ = MTSAUNet(cfg).apply(v, r, train=train, mutable=["batch_stats"])
        return out, stage1_loss(out, target, labels)

    ours, ours_loss = jax.jit(ours_fn)(variables, _image(raw, cfg))
    model = load_flax_params(MTSAUNetIdiomatic(cfg), variables).train(train)
    assert all(type(m) is torch.nn.BatchNorm2d for m in model.modules() if "BatchNorm" in type(m).__name__)
    with torch.no_grad():
        theirs = model(torch.from_numpy(raw))
        theirs_loss = stage1_loss_torch(theirs, torch.from_numpy(np.ascontiguousarray(target.transpose(0, 3, 1, 2))),
                                        torch.from_numpy(labels.astype(np.int64)))
    assert set(ours) == set(theirs)
    tol = TRAIN_TOL if train else TOL
    for key in ours:
        _assert_close(ours[key], _nhwc(theirs[key]), key, tol)
    np.testing.assert_allclose(float(ours_loss), float(theirs_loss), rtol=tol)


def _operator_calls(model, raw, target, labels) -> int:
    """aten operator calls of one train step of `model` (forward, loss, backward, AdaDelta)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        calls = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Count.calls += 1
            return func(*args, **(kwargs or {}))

    adadelta = dict(ADADELTA)
    optimizer = torch.optim.Adadelta(model.parameters(), lr=adadelta.pop("learning_rate"), **adadelta)
    step = make_torch_train_step(model, optimizer)
    with Count():
        step(raw, target, labels)
    return Count.calls


def test_fewer_operator_calls_than_the_parity_twin():
    cfg, shape = CASES["tiny"]
    variables = _random_variables("tiny")
    target, labels = _targets(cfg, shape)
    inputs = (torch.from_numpy(_raw(shape)), torch.from_numpy(np.ascontiguousarray(target.transpose(0, 3, 1, 2))),
              torch.from_numpy(labels.astype(np.int64)))
    idiomatic = _operator_calls(load_flax_params(MTSAUNetIdiomatic(cfg), variables), *inputs)
    parity = _operator_calls(load_flax_params(MTSAUNetTorch(cfg), variables), *inputs)
    # measured: 4,720 vs 5,144 (the parity twin's BatchNorm variance fix-up and |x| through `where`)
    assert idiomatic < 0.95 * parity, (idiomatic, parity)
