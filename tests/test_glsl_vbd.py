"""glsl-compute's VBD solver beyond the contract (tests/contract/test_vbd_contract.py): the SSBO
read path a driver without large buffer textures takes is as exact as the image reads, a
scene compiles only the parts it has, a PBD run none of VBD's, and a kernel shape is chosen
for VBD's own key."""

from __future__ import annotations

import json

import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.gl import compute_pbd, shapes
from clothbench.backends.tuning import TUNING_ROUNDS
from clothbench.errors import ClothbenchError
from clothbench.harness import reference, simulate
from clothbench.model.scene import load_scene
from clothbench.model.solver import Pbd, Vbd, Verlet
from conftest import assert_bit_exact, every_collider_scene, require

STRICT = BackendOptions(strict=True)


@pytest.fixture(autouse=True)
def _glsl_compute():
    require("glsl-compute")


def test_the_ssbo_reads_are_exact_too(monkeypatch):
    # the sweep reads the iterate through an imageBuffer view where the driver allows
    monkeypatch.setattr(compute_pbd, "PREFER_IMAGE_READS", False)
    scene, solver = every_collider_scene(9), Vbd(dt=1 / 60, chebyshev_rho=0.9)
    with create_backend("glsl-compute", scene, solver, STRICT) as b:
        assert not b.image_reads and "/ssbo-reads" in b.mode
    ref_pos, ref_prev = reference(scene, solver, 60, "f32")
    pos, prev = simulate("glsl-compute", scene, solver, 60, STRICT)
    assert_bit_exact(pos, ref_pos, "pos, SSBO reads")
    assert_bit_exact(prev, ref_prev, "prev, SSBO reads")


@pytest.mark.parametrize(
    "name, solver, present, absent",
    [
        (
            "drape",
            Vbd(),
            ["vbd_cloth.comp"],
            ["MOTION", "MESH_COUNT", "PIN_ATTACH", "collide_sphere.glsl", "pbd_cloth.comp"],
        ),
        ("carried", Vbd(), ["MOTION", "PIN_ATTACH", "collide_cylinder.glsl"], ["MESH_COUNT"]),
        ("torus", Vbd(), ["MESH_COUNT", "collide_mesh.glsl"], ["MOTION", "PIN_ATTACH"]),
        ("curtain", Vbd(chebyshev_rho=0.9), ["collide_sphere.glsl"], ["MOTION", "collide_cylinder.glsl"]),
        ("curtain", Pbd(), ["pbd_cloth.comp"], ["vbd_cloth.comp"]),
    ],
)
def test_a_scene_compiles_only_the_parts_it_has(name, solver, present, absent):
    # the parts: the source files a program is made of (its second line) and its switches
    scene = load_scene(name).replace(grid=8)
    if scene.meshes:
        pytest.importorskip("trimesh", reason="mesh colliders load with trimesh (pip install trimesh)")
    with create_backend("glsl-compute", scene, solver, STRICT) as b:
        sources = b.sources
    parts = set()
    for source in sources.values():
        lines = source.splitlines()
        parts.update(f.split(" ", 1)[1] for f in lines[1].removeprefix("// sources: ").split(", "))
        parts.update(line.split()[1] for line in lines if line.startswith("#define "))
    for part in present:
        assert part in parts, f"{name} {solver.name}: {part} missing"
    for part in absent:
        assert part not in parts, f"{name} {solver.name}: {part} compiled"
    if solver.name == "vbd":  # collide only with colliders, Chebyshev only with rho > 0
        collide = {"collide"} if scene.colliders or scene.meshes else set()
        chebyshev = {"chebyshev"} if solver.chebyshev_rho > 0 else set()
        assert set(sources) == {"predict", "sweep", "update"} | collide | chebyshev


def test_a_verlet_shape_choice_never_answers_a_vbd_question(monkeypatch, tmp_path):
    # both solvers' choices are kept in glsl-compute's one tuning file: VBD's key names the
    # solver and the settings that change its dispatches, so each is measured for itself
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    timed: list[str] = []

    def fake(backend, name, steps=shapes.TUNING_STEPS):  # wg=256 fastest, for every solver
        timed.append(backend.solver.name)
        return 1e-4 if name == "wg=256" else 2e-4

    monkeypatch.setattr(shapes, "time_shape", fake)
    scene = load_scene("drape").replace(grid=8)
    solvers = [Verlet(), Vbd(), Vbd(iterations=20), Vbd(substeps=2), Vbd(chebyshev_rho=0.9)]
    for solver in solvers:
        with create_backend("glsl-compute", scene, solver, STRICT) as b:
            assert b.shape == "wg=256" and b.mode.endswith("/wg=256"), b.mode
    vbd_shapes = len(shapes.candidates(scene, STRICT, "vbd"))
    assert timed.count("vbd") == 4 * TUNING_ROUNDS * vbd_shapes  # not one answered from another's
    assert len(json.loads((tmp_path / "tuning" / "glsl-compute.json").read_text())) == len(solvers)


def test_a_local_size_fixes_the_shape_and_excludes_one():
    scene = load_scene("drape").replace(grid=8)
    with create_backend("glsl-compute", scene, Vbd(), BackendOptions(local_size=32)) as b:
        assert b.shape is None and b.mode == "fast/vbd/ls=32", b.mode  # untuned, no shape in the mode
    for refused in (BackendOptions(local_size=32, shape="wg=128"), BackendOptions(shape="wg=99")):
        with pytest.raises(ClothbenchError) as e:
            create_backend("glsl-compute", scene, Vbd(), refused)
        assert "\n" not in str(e.value) and refused.shape in str(e.value)
