"""glsl-compute's VBD solver beyond the contract (tests/contract/test_vbd_contract.py): the SSBO
read path a driver without large buffer textures takes is as exact as the image reads, and a
scene compiles only the parts it has, a PBD run none of VBD's."""

from __future__ import annotations

import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.gl import compute_pbd
from clothbench.harness import reference, simulate
from clothbench.model.scene import load_scene
from clothbench.model.solver import Pbd, Vbd
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
