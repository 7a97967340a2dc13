"""Hard case 7: 1024 x 1024 (1,048,576 particles, 12.5 million springs) runs without blow-up
within memory, on every backend's first sweep variant.

Expectation: 10 steps of the sphere scene stay finite and healthy (k/m, not n, sets the
stability limit, so dt = 0.5 ms is as stable at 1024 as at 64: docs/semantics.md), and the
NumPy reference allocates at most 60 state-sized arrays at its peak (one state is
n^2 x 4 floats; pos and prev on the device side are 2 x 3 planes, the step's temporaries
about 30 more). Only each backend's first sweep variant: the modes are compared at small n.
"""

import tracemalloc

import numpy as np
import pytest

from clothbench.backends import BACKENDS, create_backend
from clothbench.harness import run_timed
from clothbench.harness.plan import plan_variants
from conftest import setup
from hard_case_variants import require

N = 1024
STEPS = 10


@pytest.mark.full
@pytest.mark.parametrize("backend", [name for name, entry in BACKENDS.items() if entry.verlet])  # a Verlet case
def test_a_million_particles_run_without_blow_up(backend):
    require(backend)
    # the first sweep variant that is not the float64 reference (numpy: f32)
    variant = next(v for v in plan_variants([backend])[0] if not v.is_reference)
    sphere = setup("sphere", N)
    tracemalloc.start()
    try:
        with create_backend(variant.backend, sphere.scene, sphere.solver, variant.options) as b:
            result = run_timed(b, STEPS, chunk=5, raise_on_blowup=False)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert result.blowup is None, str(result.blowup)
    assert result.finite and result.pos.shape == (N * N, 4)
    state_bytes = N * N * 4 * np.dtype(variant.options.dtype).itemsize
    if variant.backend == "numpy":
        assert peak <= 60 * state_bytes, f"peak {peak / 2**20:.0f} MiB"
