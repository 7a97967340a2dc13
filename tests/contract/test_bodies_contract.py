"""The backend contract for triangle meshes, moving colliders and pins attached to a body
(docs/semantics.md, "Triangle mesh", "Moving colliders", "Pins attached to a body"), on every
backend whose Capabilities take them for Verlet: strict is the NumPy float32 reference bit for
bit after contact with each mesh search it offers, in every kernel shape, build and transfer
mode; an upload starts the bodies' clock over; fast is as accurate as float32; the two mesh
searches give the same bits on thousands of triangles. What one backend compiles for a scene
(its switches, its buffers, its PTX) stays in that backend's own test file."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("trimesh", reason="the built-in mesh scenes load with trimesh (pip install trimesh)")

import trimesh

from clothbench.backends import BACKENDS, availability, backend_class, create_backend
from clothbench.model.kernel_inputs import pin_targets
from clothbench.model.colliders.mesh import Mesh
from clothbench.model.colliders.motion import Frame, Motion
from clothbench.errors import ClothbenchError
from clothbench.harness import position_error, reference, simulate
from clothbench.harness.plan import without_motion
from clothbench.model.scene import Scene, load_scene
from clothbench.model.solver import PBD_METHODS, Pbd, Vbd, solver_for_spec

from conftest import VERLET, assert_bit_exact
from registry_variants import backend_params, options, shapes_of, solver_params, usable
from test_meshes import winding_number, world_mesh  # tests/test_meshes.py: the mesh's own check

N = 32  # the contract's grid
# After contact: the torus is reached between steps 250 and 300 (at 300, 498 of the 1,024
# particles differ from the sheet without it; at 400, 1,008 by more than 1 mm), so it is read at
# 400, a hundred steps into a whole sheet's contact (500 until 2026-12-06: the steps that reach
# contact, not more); the carried sheet moves with its bar at once and reaches the sphere after
# 500; the swinging curtain reaches the paddle only at step 869 (at 700 it has not): the moving
# scenes are read at 500 and again at 1000.
CHECKPOINTS = {"torus": (400,), "sweep": (500, 1000), "carried": (500, 1000)}
FEATURE = {"torus": "meshes", "sweep": "meshes", "carried": "moving_colliders"}  # what each one needs
FULL = pytest.mark.full


def scene_named(name: str, n: int = N):
    return load_scene(name).replace(grid=n)


def searches(param) -> tuple:
    """The mesh searches a backend parameter offers, its default first ((None,) where it cannot run)."""
    name, _ = param.values[0]
    return backend_class(name).capabilities.mesh_collisions if availability(name).usable else (None,)


def body_cases(scenes=tuple(CHECKPOINTS), builds: bool = True) -> list:
    """(param, scene, search): every strict backend build that takes the scene's bodies, with each
    mesh search it offers where the scene has a mesh. The quick tier runs each backend's default
    search in its specialised build; the other search and the generic build run in the full
    tier (test_the_mesh_searches_agree_on_thousands_of_triangles holds the other search to the
    default's bits in the quick tier)."""
    cases = []
    for scene_name in scenes:
        has_mesh = bool(load_scene(scene_name).meshes)
        for param in backend_params(builds=builds, needs="strict", takes=FEATURE[scene_name]):
            name, generic = param.values[0]
            offered = searches(param)
            for search in offered if has_mesh else (None,):
                heavy = generic or search not in (None, offered[0])
                cases.append(
                    pytest.param(
                        param.values[0],
                        scene_name,
                        search,
                        id=f"{param.id}-{scene_name}-{search}",
                        marks=FULL if heavy else (),
                    )
                )
    return cases


def one_scene_each(cases: list, first=("sweep", "carried", "torus")) -> list:
    """body_cases with one scene per backend left in the quick tier, the first of `first` it
    takes (sweep: a mesh that moves, reached before its last checkpoint), the rest marked full:
    the torus's references (float64 too, 400 steps of NumPy's mesh search) are most of the cost."""
    quick: dict[str, tuple] = {}
    for case in sorted(cases, key=lambda c: first.index(c.values[1])):
        if not case.marks:
            quick.setdefault(case.values[0][0], case.values)
    return [
        pytest.param(
            *case.values, id=case.id, marks=case.marks or (() if quick[case.values[0][0]] is case.values else FULL)
        )
        for case in cases
    ]


def states(name: str, scene, values: dict, checkpoints) -> list:
    """[(steps, pos, prev)] at each checkpoint of one run from the scene's start."""
    out, done = [], 0
    with create_backend(name, scene, VERLET, options(name, **values)) as b:
        b.upload(*b.initial_state())
        for steps in checkpoints:
            b.advance(steps - done)
            done = steps
            out.append((steps, *b.read()))
    return out


def assert_reference_bits(name: str, scene, values: dict, checkpoints, what: str) -> None:
    for steps, pos, prev in states(name, scene, values, checkpoints):
        ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
        assert_bit_exact(pos, ref_pos, f"pos after {steps} steps, {name} {what}")
        assert_bit_exact(prev, ref_prev, f"prev after {steps} steps, {name} {what}")


def without_bodies(scene):
    """The scene with its meshes and motion taken away: what the bodies' effect is measured from."""
    return scene.replace(meshes=(), pin_attach=None, cylinders=tuple(c for c in scene.cylinders if c.motion is None))


def without_colliders(scene):
    """The scene with no mesh and no analytic collider, its pins fixed: the sheet when nothing is hit."""
    return scene.replace(spheres=(), cylinders=(), planes=(), meshes=(), pin_attach=None)


# --- a backend that does not take them -----------------------------------------------------


def refused_scenes(caps, solver: str) -> list:
    """(scene, the Capabilities field it needs, what a refusal names, what the backend takes instead)."""
    kinds = ", ".join(kind.name for kind in caps.collider_kinds(solver))  # colliders/kinds.py
    assert {"sphere", "cylinder", "plane"} <= set(kinds.split(", ")), kinds
    pinned = Scene(grid=4, pin_edge="top", pin_attach="f", frames=(Frame("f"),))
    return [
        (scene_named("torus", 4), "meshes", "mesh colliders", kinds),
        (scene_named("carried", 4), "moving_colliders", "moving colliders", "fixed colliders and fixed pins"),
        (pinned, "moving_colliders", "pins attached to a body", "fixed colliders and fixed pins"),
    ]


@pytest.mark.parametrize("param", solver_params())
def test_a_backend_without_the_bodies_refuses_them_in_one_line_before_any_work(param):
    name, solver = usable(param)
    cls = backend_class(name, solver)
    who = name if solver == "verlet" else f"{name} {solver}"
    for scene, feature, what, instead in refused_scenes(cls.capabilities, solver):
        if solver in getattr(cls.capabilities, feature):
            continue
        takers = [
            n
            for n, e in BACKENDS.items()
            if getattr(e, solver) and solver in getattr(backend_class(n, solver).capabilities, feature)
        ]
        assert "numpy" in takers and name not in takers
        verb = "does" if len(takers) == 1 else "do"
        want = f"{who} does not take {what} yet (it takes: {instead}; {', '.join(takers)} {verb})"
        assert cls.capabilities.scene_refusal(name, scene, solver) == want
        with pytest.raises(ClothbenchError) as e:
            cls(scene, solver_for_spec(solver, VERLET), options(name, solver))  # before its kernel is built
        assert str(e.value) == want


# --- the cases reach their bodies -----------------------------------------------------------


# the torus's 400 steps with and without its mesh, in --full; the moving bodies' two, quick
@pytest.mark.parametrize("scene_name", [pytest.param("torus", marks=FULL), "sweep", "carried"])
def test_the_bodies_change_the_reference_after_contact(scene_name):
    # not vacuous: at each checkpoint after contact the mesh, the motion or the pins on the bar
    # have moved the sheet by more than 1 mm, and by the last over a quarter of its particles
    # differ both from the sheet without its bodies and from the sheet that meets nothing
    scene = scene_named(scene_name)
    # sweep's first checkpoint comes before its paddle is reached (step 869): it checks the rest
    for steps in CHECKPOINTS[scene_name][-1:] if scene_name == "sweep" else CHECKPOINTS[scene_name]:
        ref, _ = reference(scene, VERLET, steps, "f32")
        assert position_error(ref, reference(without_bodies(scene), VERLET, steps, "f32")[0])[1] > 1e-3, steps
    for other in (without_bodies(scene), without_colliders(scene)):  # a quarter of the sheet by the last
        bare, _ = reference(other, VERLET, steps, "f32")
        assert (ref != bare).any(axis=1).sum() > scene.particles // 4, other


# --- strict: bit for bit --------------------------------------------------------------------


@pytest.mark.parametrize("param, scene_name, search", body_cases())
def test_strict_matches_numpy_f32_bit_for_bit_after_contact(param, scene_name, search):
    name, generic = usable(param)
    scene = scene_named(scene_name)
    assert_reference_bits(
        name,
        scene,
        {"strict": True, "generic": generic, "mesh_collision": search},
        CHECKPOINTS[scene_name],
        f"{scene_name} mesh={search} generic={generic}",
    )


@pytest.mark.parametrize("reach", ["300", pytest.param("after-contact", marks=FULL)])
@pytest.mark.parametrize("param, scene_name, search", body_cases(("sweep", "carried"), builds=False))
def test_every_shape_build_and_transfer_takes_the_per_step_poses_bit_for_bit(param, scene_name, search, reach):
    # each kernel shape (a multi-step one reads one table of poses per step of its launch), the
    # generic build and each transfer mode; 300 steps cross a 256-step upload of poses and end
    # inside a launch of fewer than 32 steps, and the full tier carries on past contact
    name, _ = usable(param)
    checkpoints = (300,) if reach == "300" else (300, *CHECKPOINTS[scene_name])
    scene, caps = scene_named(scene_name), backend_class(name).capabilities
    base = {"strict": True, "mesh_collision": search}
    shapes = backend_class(name).kernel_shapes(scene, options(name, **base)) if caps.shapes else ()
    builds = [{"shape": s} for s in shapes] + [{"generic": True}] * caps.generic
    builds += [{"transfer": t} for t in caps.transfers[1:]]
    for build in builds or [{}]:
        assert_reference_bits(name, scene, base | build, checkpoints, f"{scene_name} mesh={search} {build}")


@pytest.mark.parametrize("param", backend_params(takes="meshes"))
def test_the_mode_names_the_mesh_search_and_the_bvh_is_the_default(param):
    name, _ = usable(param)
    searches_offered = backend_class(name).capabilities.mesh_collisions
    if "accelerated" in searches_offered:  # the BVH traversal, where a backend has it
        assert searches_offered[0] == "accelerated", searches_offered
    torus = scene_named("torus", 16)
    with create_backend(name, torus, VERLET, options(name)) as b:
        assert b.mesh_collision == searches_offered[0] and b.mode.endswith(f"/mesh={searches_offered[0]}"), b.mode
    for search in searches_offered:
        with create_backend(name, torus, VERLET, options(name, mesh_collision=search)) as b:
            assert b.mode.endswith(f"/mesh={search}"), b.mode
    with create_backend(name, load_scene("sphere").replace(grid=16), VERLET, options(name)) as b:
        assert "/mesh=" not in b.mode and b.mesh_collision is None  # no meshes, no search


def two_meshes(n: int = 16):
    """A sheet falling onto a still icosphere and a turning box: two meshes in one buffer, the
    second read from the per-step rows."""
    return load_scene("torus").replace(
        name="two-meshes",
        grid=n,
        height=0.36,
        planes=(),
        meshes=(
            Mesh(shape="icosphere", subdivisions=1, position=(0.3, 0.0, 0.3), scale=0.3, name="ball"),
            Mesh(
                shape="box",
                position=(0.75, 0.2, 0.7),
                scale=(0.3, 0.3, 0.3),
                name="block",
                motion=Motion(angular_velocity=(0.0, 120.0, 0.0)),
            ),
        ),
    )


@pytest.mark.parametrize("param", backend_params(needs="strict", takes="meshes"))
def test_two_meshes_one_moving_match_numpy_bit_for_bit(param):
    name, _ = usable(param)
    scene, steps = two_meshes(), 400
    for search in backend_class(name).capabilities.mesh_collisions:
        with create_backend(name, scene, VERLET, options(name, strict=True, mesh_collision=search)) as b:
            if b.flushes_subnormals:  # llvmpipe's fragment shaders: this case's values pass through
                pytest.skip(f"{name} on {b.device} flushes subnormals, which this case reaches by step 20")
            b.upload(*b.initial_state())
            b.advance(steps)
            pos, prev = b.read()
        ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
        assert_bit_exact(pos, ref_pos, f"pos, {name} two meshes, mesh={search}")
        assert_bit_exact(prev, ref_prev, f"prev, {name} two meshes, mesh={search}")
    bare, _ = reference(without_bodies(scene), VERLET, steps, "f32")
    assert position_error(ref_pos, bare)[1] > 1e-3, "the meshes changed nothing"


@pytest.mark.parametrize("scene_name", ["sweep", "carried"])  # carried: its pins follow the bar from step 1
@pytest.mark.parametrize("param", backend_params(needs="strict", takes="moving_colliders"))
def test_an_upload_restarts_the_bodies_clock_and_advances_add_up(param, scene_name):
    # step k's poses are those at (k + 1) dt counted from the last upload, as NumPy counts
    # them: the same 200 steps twice from the same state give the same bits, and so do steps
    # split over advance() calls across a block of uploaded rows (7 + 250 crosses 256)
    name, _ = usable(param)
    scene = scene_named(scene_name)
    with create_backend(name, scene, VERLET, options(name, strict=True)) as b:
        runs = []
        for _ in range(2):
            b.upload(*b.initial_state())
            b.advance(200)
            runs.append(b.read())
    assert_bit_exact(runs[1][0], runs[0][0], f"{name} pos after a second upload")
    assert_bit_exact(runs[0][0], reference(scene, VERLET, 200, "f32")[0], f"{name} pos, {scene_name} 200 steps")
    small = scene_named(scene_name, 16)
    with create_backend(name, small, VERLET, options(name, strict=True)) as b:
        b.upload(*b.initial_state())
        b.advance(40)
        b.upload(*b.initial_state())  # back to t = 0
        for steps in (7, 250, 43):
            b.advance(steps)
        pos, prev = b.read()
    ref_pos, ref_prev = reference(small, VERLET, 300, "f32")
    assert_bit_exact(pos, ref_pos, f"{name} pos after an upload and advances of 7, 250, 43")
    assert_bit_exact(prev, ref_prev, f"{name} prev after an upload and advances of 7, 250, 43")


# --- fast: as accurate as float32 -----------------------------------------------------------


@pytest.mark.parametrize("param, scene_name, search", one_scene_each(body_cases(builds=False)))
def test_fast_error_is_of_the_order_of_numpy_f32s_own(param, scene_name, search):
    # Fast mode may contract FMAs and use rsqrt, division and dot() (the mesh code is the same
    # operations, contracted): each an O(float32 epsilon) change per operation, like the
    # reference's own roundings, and in contact both are amplified alike. So at 300 steps (in
    # contact with the torus) and after contact its distance to float64 is of the order of
    # NumPy float32's; 3x with a 1 um floor is the contract's bound
    # (tests/contract/test_verlet_contract.py). Measured on PoCL and llvmpipe: 0.6-1.2x.
    name, _ = usable(param)
    scene = scene_named(scene_name)
    for steps, pos, _ in states(name, scene, {"mesh_collision": search}, (300, *CHECKPOINTS[scene_name])):
        ref64 = reference(scene, VERLET, steps, "f64")[0]
        f32_rms, f32_max = position_error(reference(scene, VERLET, steps, "f32")[0], ref64)
        rms, worst = position_error(pos, ref64)
        what = f"{name} {scene_name} mesh={search} {steps} steps"
        assert worst <= 3 * max(f32_max, 1e-6), f"{what}: fast {worst:.3g} m, NumPy f32 {f32_max:.3g} m"
        assert rms <= 3 * max(f32_rms, 1e-6), f"{what}: fast RMS {rms:.3g} m, NumPy f32's {f32_rms:.3g} m"


# --- the two mesh searches ------------------------------------------------------------------


def icosphere_drop(subdivisions: int):
    """A sheet dropped from 2 cm onto an icosphere of radius 0.2 (20 * 4^s triangles)."""
    ball = Mesh(shape="icosphere", subdivisions=subdivisions, position=(0.5, 0.3, 0.5), scale=0.2, name="ball")
    return scene_named("torus").replace(meshes=(ball,), planes=(), height=0.52)


@pytest.mark.parametrize("param", backend_params(needs="strict", takes="meshes"))
def test_the_mesh_searches_agree_on_thousands_of_triangles(param):
    name, _ = usable(param)
    scene = icosphere_drop(4)
    assert scene.meshes[0].geometry.triangles == 5120
    first, *others = backend_class(name).capabilities.mesh_collisions
    if not others:
        pytest.skip(f"{name} has one mesh search ({first})")

    def run(search, s=scene):
        return states(name, s, {"strict": True, "mesh_collision": search}, (150,))[0][1:]

    want = run(first)
    for search in others:
        got = run(search)
        assert_bit_exact(got[0], want[0], f"pos, {name} {search} against {first}")
        assert_bit_exact(got[1], want[1], f"prev, {name} {search} against {first}")
    # and the mesh was touched: without it the sheet falls through where the ball is
    assert not np.array_equal(run(first, scene.replace(meshes=()))[0], want[0]), "the cloth never reached the icosphere"
    assert want[0][:, 1].min() > 0.3, "the sheet is held above the ball's centre"


# --- checked against the mesh and the body, not the reference's answer ------------------------


def outside(tm, x) -> None:
    """Every point of `x` (float64) outside the closed mesh `tm` (a winding number, independent
    of the reference's pseudo-normals), to 10 um, and the closest within 1 mm (it was touched)."""
    assert tm.is_watertight
    _, dist, _ = trimesh.proximity.closest_point_naive(tm, x)
    inside = winding_number(tm, x) > 0.5
    assert dist.min() < 1e-3, f"closest particle {dist.min():.3g} m away: the cloth never touched it"
    assert inside.sum() == 0 or dist[inside].max() <= 1e-5, f"{inside.sum()} inside, deepest {dist[inside].max():.3g} m"


@pytest.mark.parametrize("param", backend_params(takes="meshes"))
def test_cloth_dropped_on_the_torus_ends_outside_it(param):
    # 400 steps: contact from about step 200, the sheet draped over the tube by the end
    name, _ = usable(param)
    scene = scene_named("torus")
    pos = states(name, scene, {}, (400,))[0][1]
    torus = scene.meshes[0]
    tm = world_mesh(torus)
    tube = np.array([[torus.position[0] + 0.35, torus.position[1], torus.position[2]]])
    assert winding_number(tm, tube)[0] == pytest.approx(1.0, abs=1e-6)  # the check itself
    outside(tm, pos[:, :3].astype(np.float64))


@pytest.mark.parametrize("param", backend_params(takes="moving_colliders"))
def test_the_rotating_paddle_pushes_the_curtain_and_leaves_no_particle_inside(param):
    name, _ = usable(param)
    scene, steps = scene_named("sweep", 24), 1200  # 0.6 s: the curtain has swung onto the paddle's path
    pos = states(name, scene, {}, (steps,))[0][1]
    unswept = reference(scene.replace(meshes=()), VERLET, steps, "f32")[0]
    assert np.abs(pos[:, :3] - unswept[:, :3]).max() > 0.05  # the paddle did push the curtain
    paddle = world_mesh(scene.meshes[0], steps * VERLET.dt)
    x = pos[:, :3].astype(np.float64)
    inside = winding_number(paddle, x) > 0.5
    _, dist, _ = trimesh.proximity.closest_point_naive(paddle, x)
    assert inside.sum() == 0 or dist[inside].max() <= 1e-5


@pytest.mark.parametrize("strict", [True, False], ids=["strict", "fast"])
@pytest.mark.parametrize("param", backend_params(takes="moving_colliders"))
def test_the_carried_sheets_pins_are_on_the_bar_at_the_end_of_each_step_exactly(param, strict):
    # the bar's keyframes carry it 0.6 m in +z over 2 s: each pin is its start plus 0.3 t m,
    # float64 rounded once, in fast mode too (a pin is set, not stepped)
    name, _ = usable(param)
    scene, steps = scene_named("carried", 16), 1000  # 0.5 s: a quarter of the bar's travel
    pos, prev = states(name, scene, {"strict": strict}, (steps,))[0][1:]
    pinned, x0 = scene.pinned(), scene.initial_state(np.float64)[0][scene.pinned(), :3]
    for state, k, what in ((pos, steps, "pos"), (prev, steps - 1, "prev")):
        expected = (x0 + (0.0, 0.0, 0.6 * k * VERLET.dt / 2.0)).astype(np.float32)
        assert_bit_exact(pin_targets(scene, k * VERLET.dt), expected, f"pin_targets at {k} dt")
        assert_bit_exact(state[pinned, :3], expected, f"{name} {what}: the pins at t = {k} dt")
    assert (pos[pinned, 3] == 0).all(), "still pinned: inverse mass 0"
    assert (pos[pinned, 2] > x0[:, 2] + 0.05).all(), "the bar carried them"
    assert np.isfinite(pos).all()


# --- PBD (docs/pbd.md, "Colliders, motion and attached pins") ---------------------------------

PBD_N = 16  # small and fast; the spacing (6.7 cm) still drapes over the torus's 10.5 cm tube
PBD_DT = 1 / 60  # PBD's own step: at the scenes' 5e-4 s a float32 sheet at y = 1 never starts to
# fall (g h^2 at 10 substeps is below half an ulp of 1.0: x + v h rounds back to x)
# steps: the torus is touched from about step 9 (0.14 s), the paddle sweeps 45 degrees in 30,
# the bar carries the sheet 9 cm in 60
PBD_STEPS = {"torus": 30, "sweep": 30, "carried": 60}


def pbd_setup(scene_name: str, method: str = "jacobi", chebyshev_rho: float = 0.0):
    return scene_named(scene_name, PBD_N), Pbd(dt=PBD_DT, method=method, chebyshev_rho=chebyshev_rho)


def pbd_end_time(scene_name: str) -> float:
    """The collider time of the last substep: substep j ends at j * (dt / substeps), float64."""
    _, solver = pbd_setup(scene_name)
    return PBD_STEPS[scene_name] * solver.substeps * (solver.dt / solver.substeps)


def pbd_cases(solver: str = "pbd", steps: dict = PBD_STEPS) -> list:
    """(param, scene, search): every strict backend of `solver` that takes the scene's bodies,
    with each mesh search it offers where the scene has a mesh."""
    cases = []
    for scene_name in steps:
        has_mesh = bool(load_scene(scene_name).meshes)
        for param in backend_params(solver, needs="strict", takes=FEATURE[scene_name]):
            name = param.values[0][0]
            offered = backend_class(name, solver).capabilities.mesh_collisions if availability(name).usable else (None,)
            for search in offered if has_mesh else (None,):
                cases.append(pytest.param(param.values[0], scene_name, search, id=f"{param.id}-{scene_name}-{search}"))
    return cases


def assert_pbd_reference_bits(name, scene, solver, steps, search, what):
    """Strict `name` is NumPy float32 bit for bit in each of its shapes (PBD's or VBD's solver)."""
    ref_pos, ref_prev = reference(scene, solver, steps, "f32")
    for shape in shapes_of(name, scene, solver):
        opts = options(name, solver.name, strict=True, mesh_collision=search, shape=shape)
        pos, prev = simulate(name, scene, solver, steps, opts)
        assert_bit_exact(pos, ref_pos, f"pos, {name} {what} mesh={search} {shape}")
        assert_bit_exact(prev, ref_prev, f"prev, {name} {what} mesh={search} {shape}")


@pytest.mark.parametrize("method", PBD_METHODS)
@pytest.mark.parametrize("param, scene_name, search", pbd_cases())
def test_strict_pbd_matches_numpy_f32_bit_for_bit_with_bodies(param, scene_name, search, method):
    # every kernel shape: each runs the bodies' code its own way (OpenCL's Jacobi bands predict
    # the pins on the body too, its coloured vector sweep collides from its planar scratch)
    name, _ = usable(param)
    scene, solver = pbd_setup(scene_name, method)
    assert_pbd_reference_bits(name, scene, solver, PBD_STEPS[scene_name], search, f"{scene_name} {method}")


@pytest.mark.parametrize("param", backend_params("pbd", needs="strict", takes="moving_colliders"))
def test_chebyshev_jacobi_collides_bit_for_bit_too(param):
    # its multipliers ping-pong in two buffers: another launch plan around the same collide
    name, _ = usable(param)
    scene, solver = pbd_setup("sweep", "jacobi", 0.9)
    assert_pbd_reference_bits(name, scene, solver, PBD_STEPS["sweep"], "accelerated", "sweep chebyshev 0.9")


def test_the_pbd_colliders_change_the_result():
    # not vacuous: without the paddle (the same sheet, the same steps) the state differs
    scene, solver = pbd_setup("sweep")
    free, _ = reference(scene.replace(meshes=()), solver, PBD_STEPS["sweep"], "f32")
    pos, _ = reference(scene, solver, PBD_STEPS["sweep"], "f32")
    assert np.abs(pos[:, :3] - free[:, :3]).max() > 1e-2, "the paddle never reached the cloth"


@pytest.mark.parametrize("param", backend_params("pbd", needs="strict", takes="moving_colliders"))
def test_an_upload_restarts_the_pbd_bodies_clock(param):
    # substep j's poses are at j * h counted from the last upload, as NumPy counts them
    name, _ = usable(param)
    scene, solver = pbd_setup("sweep")
    with create_backend(name, scene, solver, options(name, "pbd", strict=True)) as b:
        runs = []
        for _ in range(2):
            b.upload(*b.initial_state())
            b.advance(10)
            runs.append(b.read()[0])
        b.upload(*b.initial_state())
        if b.profile_stages(10) is None:  # synchronised launch by launch, where a backend profiles
            b.advance(10)
        runs.append(b.read()[0])
    assert_bit_exact(runs[1], runs[0], f"{name}: the second run from the same state")
    assert_bit_exact(runs[2], runs[0], f"{name}: the profiled run")


@pytest.mark.parametrize("method", PBD_METHODS)
@pytest.mark.parametrize("scene_name", ["torus", "sweep"])
@pytest.mark.parametrize("param", backend_params("pbd", takes="meshes"))
def test_the_pbd_final_state_is_outside_the_mesh(param, scene_name, method):
    name, _ = usable(param)
    scene, solver = pbd_setup(scene_name, method)
    pos, _ = simulate(name, scene, solver, PBD_STEPS[scene_name], options(name, "pbd"))
    outside(world_mesh(scene.meshes[0], pbd_end_time(scene_name)), pos[:, :3].astype(np.float64))


@pytest.mark.parametrize("method", PBD_METHODS)
@pytest.mark.parametrize("param", backend_params("pbd", takes="moving_colliders"))
def test_pbd_attached_pins_sit_exactly_on_their_body(param, method):
    name, _ = usable(param)
    scene, solver = pbd_setup("carried", method)
    pos, _ = simulate(name, scene, solver, PBD_STEPS["carried"], options(name, "pbd"))
    pinned = scene.pinned()
    target = pin_targets(scene, pbd_end_time("carried"), np.float32)  # the bar's pose, float64, rounded once
    assert_bit_exact(pos[pinned, :3], target, f"{name}: the pinned particles")
    start = scene.initial_state(np.float32)[0][pinned, :3]
    assert np.abs(target - start).max() > 0.05  # the bar has moved: this is not vacuous


# --- VBD (docs/vbd.md, "Colliders, pins, and why they enter as projections") ---------------

# PBD's grid and step; 5 substeps: 60 steps are 300 substeps' poses and pin targets, more than
# one upload of them holds on the device backends (256); the torus is touched from about 0.14 s
VBD_SUBSTEPS = 5
VBD_STEPS = {"torus": 30, "sweep": 60, "carried": 60}


@pytest.mark.parametrize("param, scene_name, search", pbd_cases("vbd", VBD_STEPS))
def test_strict_vbd_matches_numpy_f32_bit_for_bit_with_bodies(param, scene_name, search):
    # the collide stage after the sweeps, at the end of each substep, and attached pins in predict
    name, _ = usable(param)
    scene = scene_named(scene_name, PBD_N)
    solver = Vbd(dt=PBD_DT, substeps=VBD_SUBSTEPS, chebyshev_rho=0.9)
    assert_pbd_reference_bits(name, scene, solver, VBD_STEPS[scene_name], search, f"{scene_name} vbd")


# the mesh's case quick; the moving paddle's and the carried pins', each two VBD references, in --full
@pytest.mark.parametrize(
    "scene_name", ["torus", pytest.param("sweep", marks=FULL), pytest.param("carried", marks=FULL)]
)
def test_the_vbd_bodies_change_the_result(scene_name):
    # not vacuous: without its mesh, or with its motion stopped, the reference ends elsewhere
    scene = scene_named(scene_name, PBD_N)
    solver = Vbd(dt=PBD_DT, substeps=VBD_SUBSTEPS, chebyshev_rho=0.9)
    pos, _ = reference(scene, solver, VBD_STEPS[scene_name], "f32")
    other = scene.replace(meshes=()) if scene.meshes else without_motion(scene)
    bare, _ = reference(other, solver, VBD_STEPS[scene_name], "f32")
    assert np.abs(pos[:, :3] - bare[:, :3]).max() > 1e-2, f"{scene_name}: the bodies never reached the cloth"
