"""glsl-compute with triangle-mesh colliders (naive loop and BVH traversal), moving colliders
and pins attached to a body (docs/semantics.md, "Triangle mesh", "Moving colliders", "Pins
attached to a body"; kernels/collide_mesh.glsl), what is its own: a scene compiles only the
switches and code of the bodies it has. The contract, for it and the fragment path (strict
bits after contact, the bodies' clock, fast error, the two searches agreeing), is
tests/contract/test_bodies_contract.py."""

from __future__ import annotations

import pytest

pytest.importorskip("trimesh", reason="the built-in mesh scenes load with trimesh (pip install trimesh)")

from clothbench.backends import BackendOptions, create_backend
from clothbench.scene import load_scene

from conftest import VERLET, require

pytestmark = pytest.mark.serial  # holds a GL context: one xdist worker


def sources(scene, **values) -> str:
    require("glsl-compute")
    with create_backend("glsl-compute", scene, VERLET, BackendOptions(strict=True, **values)) as b:
        return "\n".join(b.sources.values())


def switches(source: str) -> set[str]:
    """The names the host defines in front of the kernel (the lines before its first #line)."""
    head = source.split("#line", 1)[0]
    return {line.split()[1] for line in head.splitlines() if line.startswith("#define ")}


def test_a_scene_without_meshes_or_motion_compiles_none_of_their_code():
    source = sources(load_scene("sphere").replace(grid=16))
    assert "closest_point(" not in source and "collide_meshes(" not in source, "mesh code in a scene without meshes"
    assert not switches(source) & {"MESH_COUNT", "MOTION", "PIN_ATTACH", "MESH_BVH"}, "switches of bodies it lacks"


def test_a_still_mesh_compiles_no_motion_and_the_naive_loop_no_bvh():
    torus = load_scene("torus").replace(grid=16)
    accelerated = sources(torus)  # the default
    assert "MESH_BVH" in switches(accelerated) and "MOTION" not in switches(accelerated)
    naive = sources(torus, mesh_collision="naive")
    assert "closest_point(" in naive and not switches(naive) & {"MESH_BVH", "MOTION"}
    moving = sources(load_scene("sweep").replace(grid=16))
    assert "MOTION" in switches(moving) and "MOTION_ROW(MOTION_MESHES" in moving
