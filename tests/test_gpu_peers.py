"""The peers a GPU user would pick (torch, jax, cupy, numba-cuda), beyond the backend contract
(tests/contract/, which runs them like every backend): what each does where its framework
gets in the way of NumPy's bits, and the parts that run here without a GPU (CuPy's step on
a stand-in array module, the numba-cuda kernel under numba's CUDA simulator).

Measured here against the NumPy float32 reference (docs/peers.md): torch strict (eager),
torch fast (torch.compile, Inductor's C++) and jax strict are bit for bit; jax fast (XLA with
FMA contraction, and a division by dt as a multiplication by its reciprocal) differs from
the first step, by as much as NumPy float32 differs from float64.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import types

import numpy as np
import pytest

from clothbench.backends import BackendOptions, availability, create_backend
from clothbench.harness import position_error, reference, simulate
from clothbench.model.scene import Cylinder, Plane, Sphere, load_scene

from conftest import VERLET, assert_bit_exact, require

SHORT = 100  # steps: before contact, where float32 rounding alone sets the error


def _run(code: str, env: dict | None = None) -> subprocess.CompletedProcess:
    """`code` in a fresh Python: JAX reads its flags once per process, and numba's simulator
    must be switched on before numba.cuda is imported."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        cwd=os.path.dirname(__file__),
    )


@pytest.mark.parametrize("name", ["torch", "jax"])
def test_missing_package_is_reported_with_the_install_command(name):
    code = (
        f"import sys; sys.modules[{name!r}] = None\n"
        f"from clothbench.backends import availability\n"
        f"print(availability({name!r}).reason)"
    )
    out = _run(code)
    assert out.stdout.strip() == f"{name} not installed (pip install 'clothbench[peers]')", out.stderr


# --- torch ---------------------------------------------------------------------------------


def test_torch_strict_square_root_is_correctly_rounded():
    # strict takes the float64 root rounded once (peers/torch.py exact_sqrt): torch.sqrt's
    # vectorised float32 CPU path was one ulp off on 648 of these 1e5 values (torch 2.13)
    require("torch")
    import torch

    from clothbench.peers.torch import exact_sqrt

    a = np.abs(np.random.default_rng(0).standard_normal(100_000)).astype(np.float32)
    assert_bit_exact(exact_sqrt(torch.tensor(a)).numpy(), np.sqrt(a), "exact_sqrt")


def test_torch_fast_runs_eager_and_says_why_where_torch_compile_cannot_build(monkeypatch):
    require("torch")
    import clothbench.peers.torch as peer

    monkeypatch.setattr(peer, "_compiler_missing", lambda torch, device: "no C++ compiler for torch.compile (test)")
    scene = load_scene("sphere").replace(grid=16)
    with create_backend("torch", scene, VERLET, BackendOptions()) as b:
        assert b.mode == "fast/eager" and "no C++ compiler for torch.compile (test)" in b.driver
        b.upload(*b.initial_state())
        b.advance(SHORT)
        pos = b.read()[0]
    f32, f64 = reference(scene, VERLET, SHORT, "f32")[0], reference(scene, VERLET, SHORT)[0]
    # eager fast differs from strict only by torch.sqrt's ulp: within float32's own error
    assert position_error(pos, f64)[1] <= 3 * max(position_error(f32, f64)[1], 1e-6)


def test_torch_fast_falls_back_to_eager_when_compiling_fails_on_the_first_step(monkeypatch):
    require("torch")
    import torch

    def failing_compile(fn, **_):
        def compiled(*args):
            raise RuntimeError("InductorError: no compiler here (test)\nmore lines")

        return compiled

    monkeypatch.setattr(torch, "compile", failing_compile)
    scene = load_scene("drape").replace(grid=12)
    with create_backend("torch", scene, VERLET, BackendOptions()) as b:
        assert b.mode.endswith("/compiled")
        b.upload(*b.initial_state())
        b.advance(3)  # the first step fails to compile, runs eager, and the rest follow it
        got = b.read()
        assert b.mode == "fast/eager", b.mode
        assert "torch.compile failed, ran eager: RuntimeError: InductorError: no compiler here (test)" in b.driver
        assert "\n" not in b.driver
    import clothbench.peers.torch as peer

    monkeypatch.setattr(peer, "_compiler_missing", lambda torch, device: "eager on purpose (test)")
    want = simulate("torch", scene, VERLET, 3, BackendOptions())  # fast eager from the start
    assert_bit_exact(got[0], want[0], "three steps after a failed compile: pos")
    assert_bit_exact(got[1], want[1], "three steps after a failed compile: prev")


def test_torch_refuses_a_device_it_lacks_in_one_line():
    require("torch")
    from clothbench.errors import ClothbenchError

    with pytest.raises(ClothbenchError) as e:
        create_backend("torch", load_scene("sphere").replace(grid=8), VERLET, BackendOptions(device="nosuchdevice"))
    assert "\n" not in str(e.value) and "torch has no device 'nosuchdevice'" in str(e.value)


# --- jax -----------------------------------------------------------------------------------

_JAX_FAST_THEN_STRICT = """
    from clothbench.backends import BackendOptions, create_backend
    from clothbench.errors import ClothbenchError
    from clothbench.model.scene import load_scene
    from conftest import VERLET
    scene = load_scene("sphere").replace(grid=8)
    with create_backend("jax", scene, VERLET, BackendOptions()) as b:
        print(b.mode)
    try:
        create_backend("jax", scene, VERLET, BackendOptions(strict=True))
    except ClothbenchError as e:
        print("refused:", e)
"""


def test_jax_strict_is_refused_in_one_line_once_jax_started_with_fma():
    require("jax")
    out = _run(_JAX_FAST_THEN_STRICT, env={"XLA_FLAGS": ""})
    lines = out.stdout.strip().splitlines()
    assert lines[0] == "fast", out.stderr  # JAX's own default: FMA, no flag of ours
    assert lines[1].startswith("refused: jax --strict needs JAX started without FMA contraction"), out.stdout
    assert len(lines) == 2


def test_jax_strict_first_starts_jax_without_fma_and_fast_then_says_so():
    require("jax")
    code = """
        import os
        from clothbench.backends import BackendOptions, create_backend
        from clothbench.harness import reference
        from clothbench.model.scene import load_scene
        from conftest import VERLET, assert_bit_exact, every_collider_scene
        scene = every_collider_scene(32)  # no subnormal results in these 500 steps (XLA flushes them)
        with create_backend("jax", scene, VERLET, BackendOptions(strict=True)) as b:
            b.upload(*b.initial_state()); b.advance(500); pos = b.read()[0]
            print(b.mode)
        assert_bit_exact(pos, reference(scene, VERLET, 500, "f32")[0], "jax strict")
        with create_backend("jax", scene, VERLET, BackendOptions()) as b:
            print(b.mode)
        print(os.environ["XLA_FLAGS"])
    """
    out = _run(code, env={"XLA_FLAGS": ""})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["strict", "fast/no-fma", "--xla_cpu_max_isa=AVX"]


def test_jax_fast_with_fma_stays_within_float32_rounding():
    # In a fresh process, so JAX runs as its users get it (FMA contraction, dt's reciprocal):
    # the contract's fast test runs after its strict ones, without FMA. Measured: 5.5e-11 m off
    # NumPy float32 after one step, and after 100 steps as far from float64 as NumPy float32
    # is (8.8e-6 m on drape); held to 3x that, the contract's fast bound.
    require("jax")
    code = """
        from clothbench.backends import BackendOptions
        from clothbench.harness import position_error, reference, simulate
        from clothbench.model.scene import load_scene
        from conftest import VERLET
        for name in ("sphere", "drape"):
            scene = load_scene(name)
            f64 = reference(scene, VERLET, 100)[0]
            pos = simulate("jax", scene, VERLET, 100, BackendOptions())[0]
            print(position_error(pos, f64)[1], position_error(reference(scene, VERLET, 100, "f32")[0], f64)[1])
    """
    out = _run(code, env={"XLA_FLAGS": ""})
    assert out.returncode == 0, out.stderr
    for line in out.stdout.strip().splitlines():
        jax_max, numpy_f32_max = map(float, line.split())
        assert jax_max <= 3 * max(numpy_f32_max, 1e-6), f"jax fast {jax_max:.3g} m vs numpy f32 {numpy_f32_max:.3g} m"


# --- cupy: the NumPy step on device arrays ---------------------------------------------------


class DeviceArray(np.ndarray):
    """A stand-in for a CuPy array: NumPy arithmetic on it stays a DeviceArray, and, as CuPy
    does, an operation that mixes it with a host ndarray is a TypeError."""

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        inputs = _on_host(inputs)
        kwargs = {k: _on_host(v) for k, v in kwargs.items()}
        return _on_device(getattr(ufunc, method)(*inputs, **kwargs))

    def __array_function__(self, func, types, args, kwargs):
        return _on_device(func(*_on_host(args), **{k: _on_host(v) for k, v in kwargs.items()}))


def _on_host(x):
    if isinstance(x, DeviceArray):
        return x.view(np.ndarray)
    if type(x) is np.ndarray:
        raise TypeError(f"host array {x.shape} in a device operation")
    if isinstance(x, (tuple, list)):
        return type(x)(_on_host(v) for v in x)
    return x


def _on_device(x):
    if type(x) is np.ndarray:
        return x.view(DeviceArray)
    if isinstance(x, tuple):
        return tuple(_on_device(v) for v in x)
    return x


STAND_IN = types.SimpleNamespace(
    asarray=lambda a: np.array(a).view(DeviceArray),
    asnumpy=lambda a: np.array(a.view(np.ndarray)),
    cuda=types.SimpleNamespace(get_current_stream=lambda: types.SimpleNamespace(synchronize=lambda: None)),
)


def _stand_in_backend(scene):
    from clothbench.peers.cupy_numpy import CupyNumpyBackend

    cls = type("StandInCupy", (CupyNumpyBackend,), {"array_module": staticmethod(lambda: STAND_IN)})
    return cls(scene, VERLET, BackendOptions())


def _every_collider_kind(n: int):
    from conftest import every_collider_scene

    return every_collider_scene(n)


def test_the_stand_in_refuses_host_arrays_as_cupy_does():
    a = STAND_IN.asarray(np.ones(3, dtype=np.float32))
    assert isinstance(np.sqrt(a) + np.float32(1), DeviceArray)
    with pytest.raises(TypeError, match="host array"):
        a + np.ones(3, dtype=np.float32)
    with pytest.raises(TypeError, match="host array"):
        np.copyto(a, np.zeros(3, dtype=np.float32))


def test_cupy_peer_runs_the_numpy_step_on_device_arrays_bit_for_bit():
    # every collider kind, 500 steps (the sheet has touched each): the NumPy reference's own
    # operations, on arrays that refuse any host array left in the step
    scene = _every_collider_kind(32)
    b = _stand_in_backend(scene)
    b.upload(*b.initial_state())
    b.advance(500)
    assert isinstance(b.pos, DeviceArray) and isinstance(b.prev, DeviceArray)
    pos, prev = b.read()
    want = reference(scene, VERLET, 500, "f32")
    assert_bit_exact(pos, want[0], "pos, cupy peer on the stand-in")
    assert_bit_exact(prev, want[1], "prev, cupy peer on the stand-in")


def test_the_numpy_reference_left_on_the_host_is_caught_by_the_stand_in():
    # without the peer's conversions (the constants stay NumPy arrays) the stand-in refuses:
    # the test above can fail
    from clothbench.backends.numpy.verlet import NumpyBackend
    from clothbench.peers.cupy_numpy import CupyNumpyBackend

    class Unconverted(CupyNumpyBackend):
        def __init__(self, scene, solver, options):
            self.xp = STAND_IN
            NumpyBackend.__init__(self, scene, solver, options)

    b = Unconverted(_every_collider_kind(8), VERLET, BackendOptions())
    b.upload(*b.initial_state())
    with pytest.raises(TypeError, match="host array"):
        b.advance(1)


def test_cupy_unavailable_here_says_why():
    a = availability("cupy")
    if a.usable:
        pytest.skip(f"cupy runs here ({a.device}): the contract tests run it")
    assert a.reason.startswith(("cupy not installed", "no CUDA device", "cupy failed", "cupy cannot")), a.reason
    assert "\n" not in a.reason


# --- numba-cuda ----------------------------------------------------------------------------


def _contact_scene():
    """9 x 9 at y = 1: a sphere centred on particle (4, 4) (the exactly-at-the-centre path), a
    cylinder along row 2 (particles on its axis: the radial_r path), and a tilted plane under
    rows 7 and 8, all touched from the first step."""
    return load_scene("sphere").replace(
        grid=9,
        height=1.0,
        spheres=(Sphere((0.5, 1.0, 0.5), 0.2),),
        cylinders=(Cylinder((0.1, 1.0, 0.25), (0.9, 1.0, 0.25), 0.08),),
        planes=(Plane((0.0, 1.0, 0.8), (0.0, 1.0, -1.0)),),
        pin_corners=("top-left",),
    )


def test_the_simulator_scene_touches_every_collider_kind():
    scene = _contact_scene()
    want = reference(scene, VERLET, 4, "f32")[0]
    for kind in ("spheres", "cylinders", "planes"):
        other = reference(scene.replace(**{kind: ()}), VERLET, 4, "f32")[0]
        assert not np.array_equal(want, other), f"the sheet does not touch the {kind}"


def test_numba_cuda_kernel_matches_numpy_bit_for_bit_under_the_cuda_simulator():
    # numba's simulator runs the kernel's Python, one thread per particle, in NumPy float32
    # scalars (IEEE, no FMA, fastmath ignored): the kernel's operations and their order must
    # give NumPy's bits, in both modes. On a GPU, strict is held to that by the contract.
    pytest.importorskip("numba", reason="numba not installed (pip install 'clothbench[peers]')")
    code = """
        import numpy as np
        from clothbench.backends import BackendOptions, availability
        from clothbench.harness import reference, simulate
        from conftest import VERLET, assert_bit_exact
        from test_gpu_peers import _contact_scene
        assert availability("numba-cuda").usable, availability("numba-cuda").reason
        scene = _contact_scene()
        want = reference(scene, VERLET, 4, "f32")
        for strict in (True, False):
            got = simulate("numba-cuda", scene, VERLET, 4, BackendOptions(strict=strict))
            assert_bit_exact(got[0], want[0], f"pos strict={strict}")
            assert_bit_exact(got[1], want[1], f"prev strict={strict}")
        print("ok")
    """
    out = _run(code, env={"NUMBA_ENABLE_CUDASIM": "1"})
    assert out.stdout.strip() == "ok", out.stderr[-3000:]


def test_numba_cuda_without_a_gpu_says_why():
    a = availability("numba-cuda")
    if a.usable:
        pytest.skip(f"numba-cuda runs here ({a.device})")
    assert "\n" not in a.reason and a.reason, a.reason
