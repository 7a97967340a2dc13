"""Shared fixtures: backends skip with the reason clothbench gives, never error."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.backends import availability
from clothbench.scene import load_scene


def require(backend: str) -> None:
    """Skip the calling test with the registry's reason if `backend` cannot run here."""
    a = availability(backend)
    if not a.usable:
        pytest.skip(f"{backend} unavailable: {a.reason}")


@pytest.fixture
def sphere_scene():
    return load_scene("sphere")


@pytest.fixture
def drape_scene():
    return load_scene("drape")


def assert_bit_exact(actual: np.ndarray, expected: np.ndarray, what: str = "") -> None:
    """np.array_equal, with a readable count of differing values when it fails."""
    assert actual.dtype == expected.dtype, f"{what}: dtype {actual.dtype} != {expected.dtype}"
    if not np.array_equal(actual, expected):
        diff = actual != expected
        worst = float(np.abs(actual.astype(np.float64) - expected.astype(np.float64)).max())
        raise AssertionError(
            f"{what}: {int(diff.sum())} of {diff.size} values differ (max |diff| {worst:.3g})"
        )
