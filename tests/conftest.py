"""Shared fixtures: backends skip with the reason clothbench gives, never error."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

# Default kernel shapes, never measured ones: a test's result must not depend on which shape
# won on the machine running it (tests/test_tuning.py turns it on where it tests tuning).
os.environ["CLOTHBENCH_TUNING"] = "off"
# JAX reads XLA_FLAGS once, when a process first starts it, and jax --strict needs its CPU code
# without FMA (peers/jax.py): a test process that started JAX for a fast test first cannot run a
# strict one after it, and which tests share a process is xdist's choice. So every test process
# starts JAX without FMA; jax's fast mode is then held to its error bound without contraction
# (tests/test_gpu_peers.py checks the refusal in a process of its own, XLA_FLAGS set empty: a
# value given in the environment, even an empty one, is left as it is).
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_max_isa=AVX")
# A shell's background job starts with SIGINT ignored, and every child inherits that: a test
# that stops a child with SIGINT (tests/test_interrupts.py, tests/test_view.py's Ctrl-C) would
# wait on a child that never hears it. Each test process takes Python's own handler back, so its
# children start with the default disposition (a terminal's, or CI's)
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def _torch_with_a_workers_share_of_the_cores() -> None:
    """Each xdist worker's PyTorch on its share of the cores (one of two here), set where the
    torch peer imports it. With a pool of every core in each of two workers, every operation
    waits at its barrier for a thread the other worker's process holds: 500 steps of the strict
    64^2 drape took 40 s in the full tier on the Zen 3, 3.4 s with the two torch tests side by
    side; 1.5 ms a step on one thread beside a busy core, 4 ms on two. Nothing here is timed:
    the threads change no result (strict is bit-exact on any count, the contract)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers < 2:
        return
    import clothbench.peers.torch as torch_peer

    import_torch = torch_peer._import_torch

    def share():
        torch = import_torch()
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))
        return torch

    torch_peer._import_torch = share


_torch_with_a_workers_share_of_the_cores()

from clothbench.backends import availability
from clothbench.model.scene import Cylinder, Plane, Scene, Setup, Sphere, load_scene, load_setup
from clothbench.model.solver import Verlet
from shared_runs import share_in

# the solver every built-in scene file names: Verlet at dt = 0.5 ms, from rest
VERLET = load_setup("sphere").solver
assert VERLET == Verlet(dt=5e-4)

# The box scene every box test uses (two oriented boxes, a fixed rotated one and a moving one,
# over a sphere and a plane), and its step count, the file's: both boxes push particles within
# it in every solver, moving or stopped (tests/contract/test_box_contract.py holds that).
BOX_SCENE = Path(__file__).parent / "data" / "boxes.toml"
BOX_STEPS = load_setup(str(BOX_SCENE)).steps


# A study row's columns that say how fast, when and in which process it ran, not what it computed
# (a worker's thread settings are in env): two runs of the same study agree on every other column.
NOT_THE_RESULT = frozenset({"ms_per_step", "ms_per_sim_s", "timestamp", "env"})


def require(backend: str) -> None:
    """Skip the calling test with the registry's reason if `backend` cannot run here."""
    a = availability(backend)
    if not a.usable:
        pytest.skip(f"{backend} unavailable: {a.reason}")


def sphere(n: int) -> Scene:
    """The built-in sphere scene on an n x n grid."""
    return load_scene("sphere").replace(grid=n)


def setup(name: str, n: int | None = None) -> Setup:
    """A built-in scene file (model, solver, steps), on an n x n grid where given."""
    return load_setup(name).replace(grid=n)


def every_collider_scene(n: int) -> Scene:
    """Two spheres, two capped cylinders (one skewed, one upright: its top cap is hit), a
    tilted floor and a pinned corner; the sheet touches every one within 500 steps at n = 32
    (test_opencl.py checks)."""
    return sphere(n).replace(
        name="all-kinds",
        spheres=(Sphere((0.5, 0.5, 0.5), 0.3), Sphere((0.2, 0.62, 0.3), 0.2)),
        cylinders=(
            Cylinder((0.1, 0.75, 0.2), (0.9, 0.78, 0.3), 0.06),
            Cylinder((0.7, 0.0, 0.7), (0.7, 0.8, 0.7), 0.05),
        ),
        planes=(Plane((0.0, 0.78, 0.0), (0.1, 1.0, 0.05)),),
        pin_corners=("top-left",),
    )


def three_kinds_scene(n: int = 32) -> Scene:
    """A sphere, a cylinder and a floor that do not overlap (so no push-out can push a particle
    into another collider), all under a falling sheet: the sheet touches all three in 1500 steps."""
    return sphere(n).replace(
        height=0.8,
        spheres=(Sphere((0.3, 0.5, 0.35), 0.15),),
        cylinders=(Cylinder((0.75, 0.45, 0.15), (0.75, 0.45, 0.85), 0.1),),
        planes=(Plane((0.0, 0.25, 0.0), (0.0, 1.0, 0.0)),),
    )


def every_kind(n: int = 32) -> Scene:
    """The built-in `cylinder` scene lowered onto a sphere and a raised, tilted floor, so that
    within 300 steps all three kinds hold particles (tests/contract/test_collider_scenes_contract.py
    checks that they do)."""
    return load_scene("cylinder").replace(
        name="every-kind",
        grid=n,
        height=0.7,
        spheres=(Sphere((0.8, 0.45, 0.2), 0.2),),
        planes=(Plane((0.0, 0.6, 0.0), (0.15, 1.0, 0.0)),),
    )


def tilted_cylinder_scene(n: int = 24) -> Scene:
    """A tilted cylinder and a raised, tilted floor: at n = 24 the sheet reaches both within 600
    steps, so the side, the caps' arithmetic and the plane all run."""
    return load_scene("cylinder").replace(
        grid=n,
        cylinders=(Cylinder((0.2, 0.45, 0.45), (0.8, 0.55, 0.6), 0.15),),
        planes=(Plane((0.0, 0.55, 0.0), (0.1, 1.0, 0.05)),),
    )


def bent_state(n: int) -> tuple[Scene, np.ndarray]:
    """A sheet with hills and noise: every face a different direction."""
    scene = sphere(n)
    pos, _ = scene.initial_state(np.float64)
    rng = np.random.default_rng(10)
    pos[:, 1] += 0.2 * np.sin(3 * pos[:, 0]) * np.cos(2 * pos[:, 2]) + 0.01 * rng.standard_normal(n * n)
    pos[:, :3] += 0.002 * rng.standard_normal((n * n, 3))
    return scene, pos.astype(np.float32)


# Two tiers from one switch (README, "Tests"). `python -m pytest` is the quick tier: every
# backend's contract at small sizes, every command's happy path and its refusals. A test marked
# `full` (a long physics check or study, a study's rerun, a fault on a cluster, the layout of a
# drawn figure, a larger size's, more steps', another build's, runtime's or command's copy of a
# check the quick tier makes once) runs only with `--full`, which is what .ci/run runs. The mark
# stands on the test, its parameter or its module (`pytestmark`), where a reader of the test sees it.
def pytest_addoption(parser):
    parser.addoption("--full", action="store_true", help="also run the tests marked `full` (what CI runs)")


@pytest.hookimpl(tryfirst=True)  # before `-m` selects: the `opencl` mark must be on by then
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("serial") is not None:
            item.add_marker(pytest.mark.xdist_group("serial"))
        elif "newton" in item.nodeid and item.get_closest_marker("xdist_group") is None:
            # Newton's Warp modules compile on first use (40-50 s each on the Zen 3, cold): two
            # workers starting them at once each compiled them, where one worker pays once
            item.add_marker(pytest.mark.xdist_group("newton"))
        if "opencl" in item.nodeid:  # its file, its name or its registry parameter: CI reruns these per runtime
            item.add_marker(pytest.mark.opencl)
    if config.getoption("--full"):
        return
    full = [item for item in items if item.get_closest_marker("full") is not None]
    if full:
        config.hook.pytest_deselected(items=full)
        items[:] = [item for item in items if item.get_closest_marker("full") is None]


@pytest.fixture(scope="session", autouse=True)
def _shared_runs(tmp_path_factory) -> None:
    """Both xdist workers' float32 references and machine limits in one folder
    (tests/shared_runs.py): a worker's temporary folders lie side by side under the run's own;
    CLOTHBENCH_SHARED_RUNS names a folder several runs of the same checkout share (.ci/run's)."""
    run = tmp_path_factory.getbasetemp()
    across_runs = os.environ.get("CLOTHBENCH_SHARED_RUNS")
    share_in(
        Path(across_runs)
        if across_runs
        else (run.parent if os.environ.get("PYTEST_XDIST_WORKER") else run) / "shared-runs"
    )


@pytest.fixture
def reference_steppers(monkeypatch) -> list[str]:
    """The backend each float64 or float32 reference run is stepped by, in order, as
    harness/simulate.py's runs are made (its reference cache cleared before and after)."""
    import importlib

    runs = importlib.import_module("clothbench.harness.simulate")  # the module, not its function
    stepped_by: list[str] = []
    states = runs._states
    monkeypatch.setattr(runs, "_states", lambda backend, *a: (stepped_by.append(backend), states(backend, *a)))
    runs.reference.cache_clear()
    yield stepped_by
    runs.reference.cache_clear()


@pytest.fixture
def sphere_scene():
    return load_scene("sphere")


@pytest.fixture
def drape_scene():
    return load_scene("drape")


def wait_until(ready, proc=None, what: str = "the child to be ready", bound_s: float = 600.0) -> None:
    """Poll `ready()` until it holds: the tests that signal a child act on what the child says
    (a line it wrote, a row it finished), never after a guessed sleep. `proc` ending first fails
    at once; `bound_s` only stops a broken child from hanging the suite, it is no speed claim."""
    end = time.monotonic() + bound_s
    while not ready():
        if proc is not None and proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr else ""
            raise AssertionError(f"the child exited ({proc.returncode}) before {what}: {err}")
        if time.monotonic() > end:
            raise AssertionError(f"still waiting for {what} after {bound_s:.0f} s: the child is stuck")
        time.sleep(0.01)


def lines_in(path) -> int:
    """Lines in a file, 0 while it does not exist."""
    try:
        with open(path) as f:
            return sum(1 for _ in f)
    except FileNotFoundError:
        return 0


def drawn_text(fig) -> str:
    """Every text a matplotlib figure draws (titles, labels, footers in its subfigures), a line each."""
    from matplotlib.text import Text

    return "\n".join(t.get_text() for t in fig.findobj(Text))


def assert_bit_exact(actual: np.ndarray, expected: np.ndarray, what: str = "") -> None:
    """np.array_equal, with a readable count of differing values when it fails."""
    assert actual.dtype == expected.dtype, f"{what}: dtype {actual.dtype} != {expected.dtype}"
    if not np.array_equal(actual, expected):
        diff = actual != expected
        worst = float(np.abs(actual.astype(np.float64) - expected.astype(np.float64)).max())
        raise AssertionError(f"{what}: {int(diff.sum())} of {diff.size} values differ (max |diff| {worst:.3g})")
