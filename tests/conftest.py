"""Test setup, before JAX starts: 4 fake CPU devices for the multi-device tests, and one XLA
compilation cache per test run, shared by the tests and the CLI subprocesses they start (so each
training step compiles once per run; a fresh directory keeps the run's time honest). The trained
runs many tests read are made once per session and shared by the pytest-xdist workers."""

import atexit
import json
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
    atexit.register(shutil.rmtree, _cache + "-programs", ignore_errors=True)  # irdepth_jax.program_cache
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


def _made_once(tmp_path_factory, name: str, make):
    """`make(path)` run once per test session, whichever pytest-xdist worker asks first; the
    others wait for it and take the same path (they share the session's temporary root). A
    file lock orders them; a marker file says the result is complete."""
    import fcntl

    base = tmp_path_factory.getbasetemp()
    # under xdist each worker has its own basetemp in the session's directory; without it the
    # parent would be shared with earlier sessions
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    path, done = root / name, root / f"{name}.done"
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(path, ignore_errors=True)
            make(path)
            done.touch()
    return path


@pytest.fixture(scope="session")
def untrained_model(tmp_path_factory):
    """(workdir, unet variables, depth params) of the shared untrained tiny Stage II model
    (`trained_runs.untrained_stage2`: random UNet and Depth Anything V2), for the tests of what
    predict reads and writes."""
    from trained_runs import untrained_stage2

    from irdepth_jax.config import get_config
    from irdepth_jax.runs.variables import load_model

    work = _made_once(tmp_path_factory, "shared_untrained",
                      lambda w: untrained_stage2(w, get_config("tiny")))
    model = load_model(str(work))[2]
    for path in _read_only(work, "untrained model"):
        yield path, model["unet"], model["depth"]


@pytest.fixture(scope="session")
def synthetic_data(tmp_path_factory):
    """The shared synthetic dataset (`trained_runs.DATA`: 24 frames of 32x48, 12 labelled)."""
    from trained_runs import write_data

    yield from _read_only(_made_once(tmp_path_factory, "shared_data", write_data), "dataset")


@pytest.fixture(scope="session")
def stage1_run(synthetic_data, tmp_path_factory):
    """Workdir of the shared Stage I run: 4 + 4 steps on `synthetic_data` (`trained_runs.QUICK`:
    1 device, a checkpoint at the end of each phase)."""
    from trained_runs import train

    work = _made_once(tmp_path_factory, "shared_stage1", lambda w: train("stage1", synthetic_data, w))
    yield from _read_only(work, "Stage I run")


@pytest.fixture(scope="session")
def stage2_run(synthetic_data, stage1_run, tmp_path_factory):
    """Workdir of the shared Stage II run: 2 steps on `synthetic_data` from `stage1_run`."""
    from trained_runs import train

    work = _made_once(tmp_path_factory, "shared_stage2", lambda w: train(
        "stage2", synthetic_data, w, "--stage1-checkpoint", stage1_run))
    yield from _read_only(work, "Stage II run")


@pytest.fixture(scope="session")
def learned_run(tmp_path_factory):
    """(workdir, result) of `workflow.train_and_evaluate` on the shortened tiny config
    (`trained_runs.LEARNING`): data/, stage1/, stage2/ (with eval_test.json); result: its
    'before' and 'after' metrics."""
    from trained_runs import train_and_evaluate_learning

    def make(work):
        result = train_and_evaluate_learning(work)
        with open(f"{work}.json", "w") as f:
            json.dump({k: result[k] for k in ("before", "after")}, f, default=float)

    work = _made_once(tmp_path_factory, "learned_run", make)
    with open(f"{work}.json") as f:
        result = json.load(f)
    for path in _read_only(work, "learned run"):
        yield path, result
