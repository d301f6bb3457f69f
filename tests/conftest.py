"""Test setup, before JAX starts: 4 fake CPU devices for the multi-device tests, and one XLA
compilation cache per test run, shared by the tests and the CLI subprocesses they start (so each
training step compiles once per run; a fresh directory keeps the run's time honest)."""

import atexit
import os
import pathlib
import shutil
import tempfile

os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
).strip()
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The CLI and the experiment scripts, called in this process, would make malloc keep freed
# memory for the rest of the session (irdepth_jax.hostmem); tests/test_hostmem.py checks it in
# a process of its own.
os.environ.setdefault("IRDEPTH_DEFAULT_MALLOC", "1")
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    # made by the pytest process (with -n N, before it starts the xdist workers, which inherit
    # the variable: all share one cache) and removed when it exits
    _cache = tempfile.mkdtemp(prefix="irdepth_test_xla_")
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache

import jax  # noqa: E402  (must come after the flags above)
import pytest  # noqa: E402


@pytest.fixture(scope="session")
def four_devices():
    devices = jax.devices()
    assert len(devices) >= 4, f"expected 4 fake CPU devices, got {devices}"
    return devices[:4]


REALDATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "realdata"
"""Real thermal files (MS2 frames and lists, FLIR TIFF / .fff) beside the repository; absent in
a user's clone, where the tests that need them skip."""


@pytest.fixture(scope="session")
def realdata() -> pathlib.Path:
    if not REALDATA.is_dir():
        pytest.skip(f"real thermal test files not found at {REALDATA} (they sit beside the "
                    "repository in the project's shared folder, not in a clone)")
    return REALDATA


# --------------------------------------------------------------------------- shared trained runs
def _read_only(path, what):
    """Yields `path`; at the end of the session, fails if a test changed a file under it."""
    from trained_runs import Fingerprint

    before = Fingerprint(path)
    yield path
    changed = before.changes()
    assert not changed, (f"a test changed the shared {what} {path} (copy it with "
                         f"trained_runs.copy_run first): {changed[:10]}")


@pytest.fixture(scope="session")
def synthetic_data(tmp_path_factory):
    """The shared synthetic dataset (`trained_runs.DATA`: 24 frames of 32x48, 12 labelled)."""
    from trained_runs import write_data

    yield from _read_only(write_data(tmp_path_factory.mktemp("shared_data") / "ds"), "dataset")


@pytest.fixture(scope="session")
def stage1_run(synthetic_data, tmp_path_factory):
    """Workdir of the shared Stage I run: 4 + 4 steps on `synthetic_data` (`trained_runs.QUICK`:
    1 device, a checkpoint at the end of each phase)."""
    from trained_runs import train

    work = tmp_path_factory.mktemp("shared_stage1") / "straight"
    train("stage1", synthetic_data, work)
    yield from _read_only(work, "Stage I run")


@pytest.fixture(scope="session")
def stage2_run(synthetic_data, stage1_run, tmp_path_factory):
    """Workdir of the shared Stage II run: 2 steps on `synthetic_data` from `stage1_run`."""
    from trained_runs import train

    work = tmp_path_factory.mktemp("shared_stage2") / "s2"
    train("stage2", synthetic_data, work, "--stage1-checkpoint", stage1_run)
    yield from _read_only(work, "Stage II run")


@pytest.fixture(scope="session")
def learned_run(tmp_path_factory):
    """(workdir, result) of `workflow.train_and_evaluate` on the shortened tiny config
    (`trained_runs.LEARNING`): data/, stage1/, stage2/ (with eval_test.json)."""
    from trained_runs import train_and_evaluate_learning

    work = tmp_path_factory.mktemp("learned") / "run"
    result = train_and_evaluate_learning(work)
    for path in _read_only(work, "learned run"):
        yield path, result

