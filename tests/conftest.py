"""Test setup: 4 fake CPU devices for the multi-device tests, set before JAX starts."""

import os

os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
).strip()
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402  (must come after the flags above)
import pytest  # noqa: E402


@pytest.fixture(scope="session")
def four_devices():
    devices = jax.devices()
    assert len(devices) >= 4, f"expected 4 fake CPU devices, got {devices}"
    return devices[:4]
