"""glsl and glsl-compute (Verlet and PBD) with oriented boxes (docs/semantics.md, "Box";
kernels/collide_box.glsl), in the parts tests/contract/test_box_contract.py does not reach:
its scene moves, so it reads every box from the per-step rows; here fixed boxes are read from
the specialised program's literals and the generic program's uniforms, the response is
held to the reference on hand-placed points (ties, the centre, faces, pinned), the compute
shader's other kernel shapes read the moving rows too, fast mode is as accurate as float32,
and a program holds box code only where its scene has a box."""

from __future__ import annotations

import re

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.harness import position_error, reference, simulate
from clothbench.harness.plan import without_motion
from clothbench.model.scene import Box, load_scene, load_setup
from clothbench.model.solver import Pbd

from conftest import BOX_SCENE, BOX_STEPS, VERLET, assert_bit_exact, require, sphere

pytestmark = pytest.mark.serial  # holds a GL context: one xdist worker

# steps compared, as the contract's: both boxes are reached, still (numpy float32 moves the
# sheet with each by step 500: test_fixed_boxes_match_numpy_f32_bit_for_bit checks it) or moving
PBD = Pbd(dt=5e-4, iterations=4, substeps=2)  # the contract's PBD solver


def still_boxes():
    return without_motion(load_setup(str(BOX_SCENE)).scene)


@pytest.mark.parametrize(
    "backend, solver, generic",
    [
        ("glsl", VERLET, False),
        ("glsl", VERLET, True),
        ("glsl-compute", VERLET, False),
        ("glsl-compute", VERLET, True),
        ("glsl-compute", PBD, False),
    ],
    ids=["glsl", "glsl-generic", "glsl-compute", "glsl-compute-generic", "glsl-compute-pbd"],
)
def test_fixed_boxes_match_numpy_f32_bit_for_bit(backend, solver, generic):
    require(backend)
    scene = still_boxes()
    options = BackendOptions(strict=True, generic=generic)
    pos, prev = simulate(backend, scene, solver, BOX_STEPS, options)
    ref_pos, ref_prev = reference(scene, solver, BOX_STEPS, "f32")
    what = f"{backend} {solver.name} generic={generic} still boxes, {BOX_STEPS} steps"
    assert_bit_exact(pos, ref_pos, f"pos, {what}")
    assert_bit_exact(prev, ref_prev, f"prev, {what}")
    for i, box in enumerate(scene.boxes):  # each box did something: without it the sheet ends elsewhere
        others = scene.replace(boxes=scene.boxes[:i] + scene.boxes[i + 1 :])
        assert not np.array_equal(pos, reference(others, solver, BOX_STEPS, "f32")[0]), f"{box.name} moved nothing"


def response_scene():
    """No springs, gravity or damping: a step leaves every particle where it is (x_new = 2x - x
    exactly) and then applies the boxes, so an uploaded state is a set of points the response
    is applied to once. An unrotated box of dyadic sizes (so that ties are exact in float32)
    and a rotated one, apart."""
    return load_scene("drape").replace(
        name="box-response",
        grid=64,
        stiffness=0.0,
        damping=0.0,
        gravity=(0.0, 0.0, 0.0),
        boxes=(
            Box(center=(0.5, 0.5, 0.5), half_extents=(0.125, 0.25, 0.375)),
            Box(center=(1.5, -0.1, 0.4), half_extents=(0.3, 0.15, 0.2), rotation=(25.0, -40.0, 70.0)),
        ),
        pin_corners=(),
    )


# (point, where the box (0.5, 0.5, 0.5) +- (0.125, 0.25, 0.375) takes it, within float32's
# rounding of the face's coordinate)
HAND_PLACED = [
    ((0.6, 0.5, 0.5), (0.625, 0.5, 0.5)),  # near the +x face: out through it
    ((0.4, 0.5, 0.5), (0.375, 0.5, 0.5)),  # near the -x face
    ((0.5, 0.27, 0.5), (0.5, 0.25, 0.5)),  # near the -y face
    ((0.5, 0.5, 0.86), (0.5, 0.5, 0.875)),  # near the +z face
    ((0.5, 0.5, 0.5), (0.625, 0.5, 0.5)),  # the centre: least depth on axis 0, its + face (l = 0)
    ((0.5, 0.625, 0.5), (0.625, 0.625, 0.5)),  # depth 0.125 on x and y: the lower axis, + face
    ((0.5, 0.6875, 0.1875), (0.5, 0.75, 0.1875)),  # depth 0.0625 on y and z: the lower axis
    ((0.65, 0.5, 0.5), (0.65, 0.5, 0.5)),  # outside: not moved
    ((0.625, 0.5, 0.5), (0.625, 0.5, 0.5)),  # on a face: not strictly inside, not moved
]
PINNED = len(HAND_PLACED)  # the row after them: a pinned particle inside the first box
SCATTERED = 2000  # points over and around each box, after it


def response_state(scene) -> np.ndarray:
    rng = np.random.default_rng(28)
    state = np.ones((scene.particles, 4), np.float32)  # w = 1: free
    state[:, :3] = np.array(scene.boxes[1].center)  # the rows left over: the rotated box's centre
    state[:PINNED, :3] = [p for p, _ in HAND_PLACED]
    state[PINNED] = (0.55, 0.45, 0.5, 0.0)
    for i, box in enumerate(scene.boxes):
        first = PINNED + 1 + i * SCATTERED
        state[first : first + SCATTERED, :3] = np.array(box.center) + rng.uniform(-0.45, 0.45, (SCATTERED, 3))
    return state


@pytest.mark.parametrize("generic", [False, True], ids=["literals", "uniforms"])
@pytest.mark.parametrize("backend", ["glsl", "glsl-compute"])
def test_the_response_is_the_references_on_hand_placed_and_scattered_points(backend, generic):
    require(backend)
    scene = response_scene()
    state = response_state(scene)
    out = {}
    for name, options in (
        (backend, BackendOptions(strict=True, generic=generic)),
        ("numpy", BackendOptions(precision="f32")),
    ):
        with create_backend(name, scene, VERLET, options) as b:
            b.upload(state, state)
            b.advance(1)
            out[name] = b.read()[0]
    assert_bit_exact(out[backend], out["numpy"], f"{backend} generic={generic}: one step's response to the boxes")
    for i, (point, moved_to) in enumerate(HAND_PLACED):  # and the reference does what the spec says
        np.testing.assert_allclose(out[backend][i, :3], moved_to, atol=2e-7, rtol=0, err_msg=f"{point}")
    assert np.array_equal(out[backend][PINNED], state[PINNED]), "a pinned particle inside a box was moved"
    moved = (out[backend][:, :3] != state[:, :3]).any(axis=1)
    for i in range(len(scene.boxes)):
        first = PINNED + 1 + i * SCATTERED
        assert 100 < moved[first : first + SCATTERED].sum() < SCATTERED, "a sample holds points inside and outside"


@pytest.mark.parametrize("shape", ["wg=64", "wg=8x8", "steps/dispatch=16"])
def test_compute_shapes_read_the_moving_boxes_rows_bit_for_bit(shape):
    # the per-step rows (MOTION_BOXES) read by the two-pass, the tiled and the one-group shape
    require("glsl-compute")
    setup = load_setup(str(BOX_SCENE))
    pos, prev = simulate("glsl-compute", setup.scene, setup.solver, BOX_STEPS, BackendOptions(strict=True, shape=shape))
    ref_pos, ref_prev = reference(setup.scene, setup.solver, BOX_STEPS, "f32")
    assert_bit_exact(pos, ref_pos, f"pos, glsl-compute shape={shape} moving boxes")
    assert_bit_exact(prev, ref_prev, f"prev, glsl-compute shape={shape} moving boxes")


@pytest.mark.parametrize("backend", ["glsl", "glsl-compute"])
def test_fast_error_with_boxes_is_of_the_order_of_numpy_f32s_own(backend):
    # fast mode takes dot() for dot3 and may contract products: O(float32 epsilon) per
    # operation, amplified in contact as the reference's own roundings are; 3x NumPy float32's
    # distance to float64, with a 1 um floor, is the contract's bound (test_glsl_meshes.py)
    require(backend)
    setup = load_setup(str(BOX_SCENE))
    scene, steps = setup.scene, BOX_STEPS
    ref64, _ = reference(scene, setup.solver, steps, "f64")
    _, f32_max = position_error(reference(scene, setup.solver, steps, "f32")[0], ref64)
    pos, _ = simulate(backend, scene, setup.solver, steps, BackendOptions())
    _, fast_max = position_error(pos, ref64)
    assert fast_max <= 3 * max(f32_max, 1e-6), f"{backend}: fast {fast_max:.3g} m, numpy f32 {f32_max:.3g} m"


def program_sources(backend: str, scene, **options) -> list[str]:
    """The code (comments removed) of the programs `backend` compiles for `scene`."""
    with create_backend(backend, scene, VERLET, BackendOptions(**options)) as b:
        sources = [b.source] if backend == "glsl" else list(b.sources.values())
    return [re.sub(r"//.*", "", source) for source in sources]


@pytest.mark.parametrize("backend", ["glsl", "glsl-compute"])
def test_a_program_holds_box_code_only_where_its_scene_has_a_box(backend):
    require(backend)
    for source in program_sources(backend, sphere(16)):
        assert "collide_box" not in source and "BOX" not in source
    for source in program_sources(backend, still_boxes().replace(grid=16)):
        assert "collide_box(" in source and "#define BOX_COUNT 2" in source
        assert source.index("collide_boxes(x)") < source.index("collide_planes(x)"), "boxes act before the planes"
    for source in program_sources(backend, sphere(16), generic=True):  # generic: every kind, none yet
        assert "collide_box(" in source and "uniform int num_boxes" in source
