"""The backend contract for the VBD solver (docs/vbd.md), on every backend of the registry that
implements it: strict is the NumPy float32 reference bit for bit in every kernel shape, the
work-group size changes no bit, every mode stays within float32's reach of the float64
reference and fast within a few times NumPy float32's own error, one substep at 60 Hz holds a cloth 100 times stiffer than the scenes', and a
profile by stage names docs/vbd.md's stages."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.backends import BACKENDS, availability, backend_class, create_backend
from clothbench.harness import reference, run_timed, simulate
from clothbench.harness.simulate import position_error
from clothbench.model.scene import load_scene
from clothbench.model.solver import Vbd

from conftest import assert_bit_exact, every_collider_scene
from registry_variants import backend_params, options, shapes_of, usable
from test_pbd_contract import SCENES, STRICT_GRID, three_colliders
from test_cuda import cuda_on_cpu, shim_library  # noqa: F401  (fixtures: CUDA through its CPU build)

AT_60HZ = 1 / 60


def vbd_params(**needs) -> list:
    """backend_params("vbd", ...) and, where no CUDA device is here, CUDA once more through its
    CPU build (tests/test_cuda.py's stand-in cupy: the backend's own host code and kernel on g++)."""
    shim = [] if availability("cuda").usable else [pytest.param(("cuda", "shim"), id="cuda-shim")]
    return backend_params("vbd", **needs) + shim


def usable_here(param: tuple, request) -> tuple:
    """usable(param), or for the CUDA shim the stand-in cupy installed for this test."""
    if param[1] == "shim":
        request.getfixturevalue("cuda_on_cpu").install()
        return param
    return usable(param)


@pytest.mark.parametrize("scene_name", list(SCENES))
@pytest.mark.parametrize("param", vbd_params(needs="strict"))  # NumPy is the reference itself
def test_strict_vbd_matches_numpy_f32_bit_for_bit_after_200_steps(param, scene_name, request):
    # docs/vbd.md fixes every operation's order, the LDL^T solve's included; within a colour no
    # particle reads another of its colour, so however a kernel spreads a colour over work
    # items, each particle computes the same bits
    name, _ = usable_here(param, request)
    scene, solver = SCENES[scene_name](STRICT_GRID), Vbd(dt=AT_60HZ, chebyshev_rho=0.9)
    ref_pos, ref_prev = reference(scene, solver, 200, "f32")
    for shape in shapes_of(name, scene, solver):
        pos, prev = simulate(name, scene, solver, 200, options(name, "vbd", strict=True, shape=shape))
        assert_bit_exact(pos, ref_pos, f"{name} {shape} vbd {scene_name} pos")
        assert_bit_exact(prev, ref_prev, f"{name} {shape} vbd {scene_name} prev")


@pytest.mark.parametrize("param", vbd_params(needs="local_size"))
def test_work_group_size_changes_no_strict_vbd_bit(param, request):
    # 7 divides neither n*n nor a colour's particles: launches are padded and the extra items return
    name, _ = usable_here(param, request)
    scene, solver = three_colliders(13), Vbd(dt=AT_60HZ)
    ref = reference(scene, solver, 30, "f32")[0]
    for ls in (7, 128):
        for shape in shapes_of(name, scene, solver, local_size=ls):
            pos = simulate(name, scene, solver, 30, options(name, "vbd", strict=True, local_size=ls, shape=shape))[0]
            assert_bit_exact(pos, ref, f"{name} vbd {shape} local size {ls}")


@pytest.mark.full  # a looser bound than the fast-error test's below, which the quick tier runs
@pytest.mark.parametrize("param", vbd_params())
def test_vbd_f32_stays_within_float32_of_the_f64_reference(param, request):
    # 60 steps of a sheet across every collider kind: numpy f32 is 7e-7 m RMS from f64 there. A
    # fast mode may reorder and contract, so the bound is 1e-4 m: a wrong step is centimetres
    # off. (The curtain is not used: its contact with the sphere turns one particle pushed a
    # step earlier into 1.7e-4 m by step 60, even for numpy f32.)
    name, _ = usable_here(param, request)
    if BACKENDS[name].peer:
        pytest.skip(f"{name} is a peer: it runs its own model of the springs and contacts, held by physics elsewhere")
    scene, solver = three_colliders(16), Vbd(dt=AT_60HZ)
    ref = reference(scene, solver, 60, "f64")[0]
    pos = simulate(name, scene, solver, 60, options(name, "vbd"))[0]
    assert position_error(pos, ref)[0] < 1e-4


# every collider kind; a mesh; pins on a moving bar (with what each needs a backend to take)
FAST_SCENES = {"all kinds": None, "torus": "meshes", "carried": "moving_colliders"}


@pytest.mark.parametrize("scene_name", list(FAST_SCENES))
@pytest.mark.parametrize("param", vbd_params(needs="strict"))  # those with a fast mode
def test_fast_vbd_error_is_of_the_order_of_numpy_f32s_own(param, scene_name, request):
    # Fast contracts FMAs and takes one 1/sqrt per spring: O(float32 epsilon) per operation, as
    # the reference's own roundings. Measured (16^2, 60 steps at 60 Hz, 10 sweeps; PoCL 3.1 and
    # llvmpipe 15, 2026-12-04): fast's max error from f64 is 1.3-4.4x NumPy f32's (2-8 um). The
    # bound, 8x with a 2 um floor, still catches a slip in the step: 1% on k alone puts NumPy
    # f32 0.3-2 mm off, 10% on b 0.9-22 mm. Not with Chebyshev or the curtain: contact there
    # turns one particle pushed a substep earlier into millimetres.
    name, _ = usable_here(param, request)
    feature = FAST_SCENES[scene_name]
    if feature is not None and "vbd" not in getattr(backend_class(name, "vbd").capabilities, feature):
        pytest.skip(f"{name} vbd does not take {feature}")
    if scene_name == "all kinds":
        scene = every_collider_scene(16)
    else:
        scene = load_scene(scene_name).replace(grid=16)
        if scene.meshes:
            pytest.importorskip("trimesh", reason="mesh colliders load with trimesh (pip install trimesh)")
    solver = Vbd(dt=AT_60HZ)
    ref64 = reference(scene, solver, 60, "f64")[0]
    _, f32_max = position_error(reference(scene, solver, 60, "f32")[0], ref64)
    _, fast_max = position_error(simulate(name, scene, solver, 60, options(name, "vbd"))[0], ref64)
    assert fast_max <= 8 * f32_max + 2e-6, f"{name} {scene_name}: fast {fast_max:.3g} m, NumPy f32 {f32_max:.3g} m"


@pytest.mark.parametrize("param", vbd_params())
def test_vbd_holds_stiffness_1e5_at_60hz_in_one_substep(param, request):
    # issue 33's goal: implicit Euler takes a step far past Verlet's dt <= 2/omega (tests/test_vbd.py
    # shows Verlet blowing up there); run_timed raises BlowUp if it does not hold
    name, _ = usable_here(param, request)
    scene, solver = SCENES["curtain"](16).replace(stiffness=1e5), Vbd(dt=AT_60HZ, substeps=1)
    with create_backend(name, scene, solver, options(name, "vbd")) as b:
        pos = run_timed(b, 120).pos
    assert np.isfinite(pos).all()
    assert pos[:, 1].min() > scene.height - 2 * scene.size  # hangs within the sheet's length


@pytest.mark.parametrize("param", backend_params("vbd"))
def test_a_vbd_profile_names_every_stage_and_changes_no_bit(param):
    # where a backend profiles (a device's synchronised launches), each stage of docs/vbd.md's
    # substep is timed, and the profiled steps are the steps
    name, _ = usable(param)
    scene, solver = SCENES["curtain"](13), Vbd(dt=AT_60HZ, chebyshev_rho=0.9)
    runs, stages = [], None
    for profiled in (False, True):
        with create_backend(name, scene, solver, options(name, "vbd", strict=True)) as b:
            b.upload(*b.initial_state())
            stages = b.profile_stages(3) if profiled else b.advance(3)
            runs.append(b.read()[0])
    if stages is None:
        pytest.skip(f"{name} does not profile by stage")
    assert set(stages) == {"predict", "sweep", "chebyshev", "collide", "update"}
    assert all(ms >= 0 for ms in stages.values())
    assert_bit_exact(runs[1], runs[0], f"{name}: the profiled steps")
