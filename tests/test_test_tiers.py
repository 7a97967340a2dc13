"""The test suite's own machinery (README, "Tests"; tests/conftest.py): what keeps its tiers and
its workers honest."""

from __future__ import annotations

import os

import pytest


@pytest.mark.serial
def test_a_serial_test_runs_in_the_serial_group_of_its_worker(request):
    # pytest-xdist's loadgroup sends every test of a group to one worker by naming its node
    # "<id>@<group>"; where that name does not take (pytest 9.2 with xdist 3.8: xdist#1386) the
    # group silently goes and the GL and timing tests run on both workers at once
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        pytest.skip("one process (-n 0): there are no workers to group")
    assert request.node.nodeid.endswith("@serial"), f"{request.node.nodeid}: the serial group did not take"


def test_torch_in_a_worker_runs_on_that_worker_s_share_of_the_cores():
    # tests/conftest.py: every core in each of two workers' pools made each operation wait at its
    # barrier for a thread the other worker held (40 s for what runs in 2 s)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers < 2:
        pytest.skip("one process (-n 0): torch keeps its own thread count")
    pytest.importorskip("torch", reason="the torch peer is not installed (pip install 'clothbench[peers]')")
    from clothbench.peers.torch import _import_torch

    assert _import_torch().get_num_threads() == max(1, (os.cpu_count() or 1) // workers)
