"""The benchmarks' own pieces: the Stage II loss both sides time is the same function, and the
host-side benchmark runs (tiny sizes; the figures come from experiments/, not from tests)."""

import numpy as np
import pytest

from irdepth_jax.losses import silog_loss


def test_the_official_side_times_our_silog_loss():
    torch = pytest.importorskip("torch", reason="the PyTorch side needs torch (the [torch] extra)")
    from irdepth_experiments.bench_depth_anything import silog_loss_torch

    rng = np.random.default_rng(0)
    pred, depth = rng.uniform(0.5, 80, (2, 2, 14, 28)).astype(np.float32)
    valid = rng.random((2, 14, 28)) < 0.7
    theirs = silog_loss_torch(*(torch.from_numpy(a) for a in (pred, depth, valid))).item()
    d = np.log(depth[valid].astype(np.float64)) - np.log(pred[valid])
    by_hand = np.sqrt(np.mean(d**2) - 0.5 * np.mean(d) ** 2)
    np.testing.assert_allclose(theirs, by_hand, rtol=1e-5)
    np.testing.assert_allclose(float(silog_loss(pred, depth, valid)), by_hand, rtol=1e-5)


def test_loader_benchmark_reports_the_three_rates(tmp_path):
    from irdepth_experiments.bench_loader import main

    out = tmp_path / "loader.json"
    result = main(["--preset", "tiny", "--size", "32x48", "--frames", "16", "--steps", "2",
                   "--repeats", "1", "--json", str(out)])
    for key in ("step_alone_img_per_s", "loader_alone_img_per_s", "training_img_per_s"):
        assert result[key] > 0, key
    assert result["batch"] == 4 and out.exists()
    assert result["training_over_step_alone"] == pytest.approx(
        result["training_img_per_s"] / result["step_alone_img_per_s"])


@pytest.mark.parametrize("what", ["forward", "forward+backward"])
def test_attention_benchmark_sides_compute_the_same(what):
    pytest.importorskip("torch", reason="the PyTorch side needs torch (the [torch] extra)")
    import jax.numpy as jnp

    from irdepth_experiments.bench_attention import HEAD_DIM, HEADS, ours_call, torch_calls

    rng = np.random.default_rng(0)
    q, k, v, g = (jnp.asarray(rng.standard_normal((2, HEADS, 37, HEAD_DIM), np.float32)) for _ in range(4))
    as_list = (lambda out: [out]) if what == "forward" else list  # the output, or dq, dk, dv
    ours = as_list(ours_call(what, q, k, v, g)())
    for name, call in torch_calls(what, q, k, v, g).items():
        theirs = as_list(call())
        assert len(theirs) == len(ours)
        for a, b in zip(ours, theirs):
            np.testing.assert_allclose(np.asarray(a), b.numpy(), rtol=1e-4, atol=1e-5, err_msg=name)


class _FakeWorker:
    """Stands in for bench_common.Worker: fixed seconds per call, and a count of the processes
    that would be alive at once."""

    alive = 0
    most_alive = 0

    torch_flops = {"fwd_torch_flops": 1.96e9, "train_torch_flops": 5.9e9}

    def __init__(self, setup, *args, threads, keep_memory=True, **kwargs):
        self.name = setup.__name__
        self.kwargs = kwargs
        # train: the step timed executes fewer FLOPs (Winograd kernel gradients) than the model's
        # nominal count, which equal work is checked on
        self.info = {"fwd_flops": 2e9, "train_flops": 4.5e9, "train_nominal_flops": 6e9, "threads": threads}
        if self.name == "setup_twin":
            self.info.update(self.torch_flops)

    def __enter__(self):
        type(self).alive += 1
        type(self).most_alive = max(type(self).most_alive, type(self).alive)
        return self

    def __exit__(self, *exc):
        type(self).alive -= 1

    def time(self, name):
        seconds = {"forward": 0.5, "train": 2.0, "matmul": 0.1}[name]
        return seconds * (1.0 if self.name == "setup_ours" else 1.25)

    def result(self, name):
        outputs = {"recon": np.zeros((1, 4, 4, 1), np.float32)}
        if self.name == "setup_ours":
            return outputs
        return {k: v.transpose(0, 3, 1, 2) + 1e-3 for k, v in outputs.items()}  # NCHW, as torch


@pytest.mark.parametrize("one_at_a_time", [False, True])
def test_unet_benchmark_one_at_a_time_never_holds_both_sides(monkeypatch, one_at_a_time):
    from irdepth_experiments import bench_unet

    monkeypatch.setattr(bench_unet, "Worker", _FakeWorker)
    _FakeWorker.alive = _FakeWorker.most_alive = 0
    result = bench_unet.bench_case(("tiny", True), (4, 4), 1, repeats=2, warmup=1, threads=2,
                                   with_torch=True, peak_size=64, one_at_a_time=one_at_a_time)
    assert _FakeWorker.most_alive == (1 if one_at_a_time else 2)
    assert result["interleaved"] is not one_at_a_time
    assert result["fwd_ours_ms"] == pytest.approx(500) and result["train_torch_ms"] == pytest.approx(2500)
    assert result["train_ours_over_torch"] == pytest.approx(0.8)
    assert result["fwd_max_abs_diff"] == pytest.approx(1e-3)
    assert result["train_ours_gflops"] == pytest.approx(2.25)  # of the executed FLOPs (4.5 / 2 s)
    assert result["train_xla_over_torch_flops"] == pytest.approx(6 / 5.9)  # of the nominal ones
    assert result["matmul_peak"]["torch_gflops"] == pytest.approx(2 * 64**3 / 0.125 / 1e9)
    assert result["fwd_xla_over_torch_flops"] == pytest.approx(2 / 1.96)
    assert result["train_ours_seconds"]["spread_pct"] == pytest.approx(0.0)


def test_unet_benchmark_refuses_unequal_work(monkeypatch):
    from irdepth_experiments import bench_unet

    monkeypatch.setattr(bench_unet, "Worker", _FakeWorker)
    # the opponent counts 20 % fewer train-step FLOPs than XLA: not the same work
    monkeypatch.setattr(_FakeWorker, "torch_flops", {"fwd_torch_flops": 2e9, "train_torch_flops": 5e9})
    with pytest.raises(RuntimeError, match="unequal work: train"):
        bench_unet.bench_case(("tiny", True), (4, 4), 1, repeats=1, warmup=0, threads=2,
                              with_torch=True, peak_size=None)


def test_bounds_work_out_the_rate_a_target_needs():
    from irdepth_experiments.bench_bounds import target_rows

    unet = {"preset": "paper", "matmul_peak": {"xla_gflops": 200.0},
            "results": [{"size": [256, 320], "batch": 4, "fwd_flops": 1e11, "train_flops": 4e11,
                         "fwd_ours_ms": 500.0, "fwd_torch_ms": 1000.0,
                         "train_ours_ms": 4000.0, "train_torch_ms": 2500.0}]}
    fwd, train = target_rows(unet, target=0.8)
    # forward: 100 GFLOP in 0.5 s = 200 GFLOP/s (100 % of the peak); the target 0.8 x 1 s = 0.8 s
    # needs 125 GFLOP/s = 62.5 %
    assert fwd["what"] == "MTSA-UNet paper forward, 256x320, batch 4"
    assert fwd["target_ms"] == pytest.approx(800.0) and fwd["ratio"] == pytest.approx(0.5)
    assert fwd["ours_gflops"] == pytest.approx(200.0) and fwd["ours_peak_pct"] == pytest.approx(100.0)
    assert fwd["needed_gflops"] == pytest.approx(125.0) and fwd["needed_peak_pct"] == pytest.approx(62.5)
    # train step: 400 GFLOP by 0.8 x 2.5 s = 2 s: 200 GFLOP/s, the whole peak
    assert train["needed_peak_pct"] == pytest.approx(100.0) and train["ratio"] == pytest.approx(1.6)

    depth = {"encoder": "vits", "matmul_peak": {"xla_gflops": 100.0},
             "results": [{"reference": "official", "batch": 2, "kind": "train_step", "size": [518, 518],
                          "ours_ms": 2000.0, "theirs_ms": 1000.0, "ours_gflops": 50.0, "ours_over_theirs": 2.0}]}
    (row,) = target_rows(depth, target=0.5)
    # 50 GFLOP/s for 2 s = 100 GFLOP; in 0.5 x 1 s it needs 200 GFLOP/s, twice the peak
    assert row["gflop"] == pytest.approx(100.0) and row["needed_peak_pct"] == pytest.approx(200.0)
    assert row["what"] == "Depth Anything V2 vits train step, 518x518, batch 2 vs official"
    with pytest.raises(ValueError, match="not a bench_unet"):
        target_rows({"results": []})


def test_bounds_read_the_committed_results(capsys):
    from irdepth_experiments.bench_bounds import main

    rows = main([])
    assert len(rows) >= 8 and all(0 < r["needed_peak_pct"] < 1000 for r in rows)
    assert "% needed" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no such file"):
        main(["no-such-file.json"])
