"""The OpenCL VBD solver beyond the contracts (tests/contract/test_vbd_contract.py, and
test_bodies_contract.py for its meshes, moving colliders and attached pins): strict is the
NumPy float32 reference bit for bit on every runtime here that compiles; a scene compiles only
the parts it has."""

from __future__ import annotations

import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.opencl import device
from clothbench.harness import reference, simulate
from clothbench.model.scene import load_setup
from clothbench.model.solver import Vbd
from conftest import assert_bit_exact, require

N = 16  # as tests/test_pbd_meshes.py: the spacing still drapes over the torus's tube


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


def scene_of(name: str):
    """Built-in scene `name` at N, or a skip where it has meshes and trimesh is missing."""
    scene = load_setup(name).scene.replace(grid=N)
    if scene.meshes:
        pytest.importorskip("trimesh", reason="mesh colliders load with trimesh (pip install trimesh)")
    return scene


def test_strict_vbd_is_bit_exact_on_every_runtime_here_that_compiles():
    # the Intel CPU runtime as well as PoCL: no runtime may contract or reorder a strict build
    scene, solver = load_setup("curtain").scene.replace(grid=24), Vbd(dt=1 / 60, chebyshev_rho=0.9)
    ref_pos, ref_prev = reference(scene, solver, 100, "f32")
    compiling = [(spec, kind) for spec, dev, kind in device.ordered_devices() if device.compile_error(dev) is None]
    assert compiling, "no OpenCL device here compiles"
    for spec, kind in compiling:
        pos, prev = simulate("opencl", scene, solver, 100, BackendOptions(strict=True, device=spec))
        assert_bit_exact(pos, ref_pos, f"pos, {kind} ({spec})")
        assert_bit_exact(prev, ref_prev, f"prev, {kind} ({spec})")


def test_a_scene_compiles_only_the_parts_it_has():
    cases = {
        "drape": (),
        "torus": ("-DCLOTH_MESHES=1", "-DCLOTH_MESH_BVH"),
        "carried": ("-DCLOTH_PER_STEP", "-DCLOTH_ATTACHED_PINS"),
    }
    parts = ("CLOTH_MESHES", "CLOTH_MESH_BVH", "CLOTH_PER_STEP", "CLOTH_ATTACHED_PINS")
    for name, expected in cases.items():
        scene, solver = scene_of(name), Vbd(dt=1 / 60)
        with create_backend("opencl", scene, solver, BackendOptions(strict=True)) as b:
            built = b.build_options()
            has_mesh_code = "closest_point" in b.source
        found = {o.split("=")[0] for o in built if any(o.startswith(f"-D{p}") for p in parts)}
        assert found == {o.split("=")[0] for o in expected}, f"{name}: {built}"
        assert has_mesh_code == bool(scene.meshes), f"{name}: mesh code in the source"
