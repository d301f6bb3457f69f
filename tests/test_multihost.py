"""Two processes x 2 CPU devices (jax.distributed on localhost) = the single-process run."""

import json
import os
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest
from test_parallel import run

WORKER = r'''
import json, os, sys
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
os.environ["JAX_PLATFORMS"] = "cpu"
process_id, port, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
sys.path.insert(0, sys.argv[4])
import jax
import numpy as np
from irdepth_jax.train.parallel import DataParallel, initialize_distributed
initialize_distributed(f"localhost:{port}", 2, process_id)
from test_parallel import Toy, make_batch, make_state, toy_loss
from irdepth_jax.train.steps import make_train_step

dp = DataParallel("shard_map")
assert dp.num_devices == 4 and dp.local_devices == 2, (dp.num_devices, dp.local_devices)
step = dp.train_step(make_train_step(toy_loss(Toy(dp.axis_name)), dp.axis_name, 1))
state = dp.replicate(make_state())
history = []
for i in range(2):
    batch = make_batch(seed=i)                 # the global batch of 16 ...
    rows = slice(process_id * 8, (process_id + 1) * 8)
    local = {k: v[rows] for k, v in batch.items()}   # ... of which this process loads its half
    state, metrics = step(state, dp.shard_batch(local), None)
    history.append(dp.metrics_to_host(metrics))
host = dp.unreplicate(state)
flat = {jax.tree_util.keystr(p): np.asarray(v).tolist()
        for p, v in jax.tree_util.tree_flatten_with_path(
            {"params": host.params, "batch_stats": host.batch_stats})[0]}
with open(out, "w") as f:
    json.dump({"history": history, "state": flat, "step": int(host.step)}, f)
'''


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.multidevice
def test_two_processes_agree_with_one(tmp_path, four_devices):
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS",)}
    tests_dir = os.path.dirname(os.path.abspath(__file__))
    procs = [subprocess.Popen([sys.executable, str(script), str(i), str(port),
                               str(tmp_path / f"out{i}.json"), tests_dir],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    logs = []
    try:
        for p in procs:
            logs.append(p.communicate(timeout=240)[0])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]

    single_state, single_history = run("single", steps=2)
    flat = {jax.tree_util.keystr(p): np.asarray(v) for p, v in jax.tree_util.tree_flatten_with_path(
        {"params": single_state.params, "batch_stats": single_state.batch_stats})[0]}
    for i in range(2):
        got = json.loads((tmp_path / f"out{i}.json").read_text())
        assert got["step"] == 2
        for mine, ref in zip(got["history"], single_history):
            for k in ("loss", "mae", "grad_norm"):
                np.testing.assert_allclose(mine[k], ref[k], rtol=1e-5, err_msg=k)
        assert set(got["state"]) == set(flat)
        for key, ref in flat.items():
            np.testing.assert_allclose(np.asarray(got["state"][key]), ref, rtol=1e-5, atol=1e-6,
                                       err_msg=key)


CLI = "import sys; from irdepth_jax.cli import main; sys.exit(main(sys.argv[1:]))"


def _cli_processes(runs, tmp_path, returncode=0):
    """Runs `irdepth argv` for each (argv, CPU devices of that process) in `runs`, all at once;
    returns their outputs after each exited with `returncode`."""
    procs = []
    for argv, devices in runs:
        env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
        env.update(JAX_PLATFORMS="cpu", XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")
        procs.append(subprocess.Popen([sys.executable, "-c", CLI, *map(str, argv)], env=env,
                                      cwd=tmp_path, stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True))
    try:
        logs = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for (argv, _), p, log in zip(runs, procs, logs):
        assert p.returncode == returncode, f"{argv}:\n{log[-3000:]}"
    return logs


@pytest.mark.multidevice
def test_cli_train_on_two_processes_equals_one_process_with_two_devices(synthetic_data, tmp_path):
    """docs/usage.md's cluster command on localhost: `irdepth train --coordinator ... --num-processes 2
    --process-id i` (one CPU device each, one shared workdir) trains Stage I-1 to the same losses
    and weights as one process with `--devices 2`. The three processes run at once, and stop
    (`--stop-at`) after I-1, whose checkpoint is compared: I-2 runs the same parallel code."""
    from test_cli import final_params, read_metrics
    from trained_runs import MODEL, QUICK

    from irdepth_jax.cli import EXIT_INTERRUPTED

    quick = [a for a in QUICK if a not in ("--devices", "1")]  # QUICK's two-level UNet
    common = ["train", "stage1", "--data", synthetic_data, "--steps", 2, "--stop-at", 2, *quick]
    one, two = tmp_path / "one_process", tmp_path / "two_processes"
    port = free_port()
    logs = _cli_processes(
        [([*common, "--workdir", two, "--coordinator", f"localhost:{port}", "--num-processes", 2,
           "--process-id", i], 1) for i in range(2)]
        + [([*common, "--workdir", one, "--devices", 2], 2)], tmp_path, EXIT_INTERRUPTED)
    assert "irdepth: stage1: parallel: shard_map over 2 devices (2 processes x 1)" in logs[0], logs[0]
    assert "stopped at step 2: stage1_i1 checkpoint at step 2" in logs[0], logs[0]

    rows_one, rows_two = read_metrics(one), read_metrics(two)
    assert [r.get("step") for r in rows_two] == [r.get("step") for r in rows_one]
    losses = [(r, s) for r, s in zip(rows_one, rows_two) if "loss" in r]
    assert len(losses) == 2  # 2 steps of I-1
    for ref, got in losses:
        for key in ("loss", "recon", "grad_norm"):
            np.testing.assert_allclose(got[key], ref[key], rtol=1e-5, err_msg=key)
    ref_model, _ = final_params(one, "stage1_i1", MODEL)
    got_model, _ = final_params(two, "stage1_i1", MODEL)
    ref_leaves = jax.tree_util.tree_leaves_with_path(ref_model)
    got_leaves = jax.tree.leaves(got_model)
    assert len(ref_leaves) == len(got_leaves)
    for (path, ref), got in zip(ref_leaves, got_leaves):
        np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=1e-5, atol=1e-6,
                                   err_msg=jax.tree_util.keystr(path))
