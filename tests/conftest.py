"""Shared fixtures: the OpenCL device (PoCL in CI), fp64 skip helper, shared data location."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from triplet_cl.device import get_device
from triplet_cl.errors import NoOpenCLPlatformError

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def device():
    """The device the suite runs on (``$TRIPLET_DEVICE`` or the default choice)."""
    try:
        return get_device()
    except NoOpenCLPlatformError as exc:  # pragma: no cover - CI installs PoCL
        pytest.fail(str(exc))


@pytest.fixture(scope="session")
def device64(device):
    """The same device, for float64 gradient checks; skips where there is no cl_khr_fp64."""
    if not device.fp64:
        pytest.skip(f"device {device.name!r} has no fp64 support (cl_khr_fp64)")
    return device


@pytest.fixture(scope="session")
def bitwise(device) -> bool:
    """Whether the suite's bit-for-bit comparisons apply on this device: PoCL's (CI's) float arithmetic is what
    they were written against (correctly rounded division and square root, the FP_CONTRACT pragma honoured, one
    build's rounding in every program variant). Elsewhere the same tests compare within a few ulp: on NVIDIA's
    OpenCL (H200, session 51) the exact device loss differed from numpy by 1-16 ulp on a fifth of the values, and
    two builds of the shading kernel (packed and separate inputs) by a few ulp."""
    return "portable computing language" in device.platform.name.lower()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def shared_data():
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA
