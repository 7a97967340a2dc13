"""OpenCL's PBD with meshes, moving colliders and pins attached to a body (docs/pbd.md,
"Colliders, motion and attached pins"), what is its own: every kernel shape is offered with
bodies, and a scene compiles only the parts it has. The contract (strict bits with either
search, method and shape; the bodies' clock; the final state outside the mesh; pins on their
body) is tests/contract/test_bodies_contract.py."""

from __future__ import annotations

import functools

import pytest

pytest.importorskip("trimesh", reason="mesh colliders load with trimesh (pip install trimesh)")

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.opencl.pbd import OpenCLPbdBackend
from clothbench.scene import load_setup
from clothbench.solver import Pbd
from conftest import require

METHODS = ("jacobi", "coloured")


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


@functools.lru_cache(maxsize=None)
def setup(name: str, method: str = "jacobi"):
    """The contract's PBD case (tests/contract/test_bodies_contract.py): 16 x 16, PBD's own step."""
    return load_setup(name).scene.replace(grid=16), Pbd(dt=1 / 60, method=method)


# --- OpenCL's kernel shapes run the bodies' code ----------------------------------------------


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", ["torus", "sweep", "carried"])
def test_every_opencl_shape_is_offered_with_bodies(name, method):
    # the contract runs each shape offered (tests/contract/test_bodies_contract.py): the bands
    # (Jacobi) predict the pins on the body too, the coloured vector sweep collides from its
    # planar scratch, so those are among them
    scene, solver = setup(name, method)
    jacobi = method == "jacobi"
    for search in ("naive", "accelerated") if scene.meshes else (None,):
        shapes = OpenCLPbdBackend.kernel_shapes(scene, BackendOptions(strict=True, mesh_collision=search), solver)
        assert {"per-stage", "one-launch"} <= set(shapes)
        assert jacobi == ("bands-8" in shapes) and jacobi != ("one-launch-vectors" in shapes), shapes


# --- only what the scene has is compiled -------------------------------------------------------


def test_a_scene_compiles_only_the_body_code_it_has():
    built = {}
    for name in ("curtain", "torus", "sweep", "carried"):
        scene, solver = setup(name)
        with create_backend("opencl", scene, solver, BackendOptions(strict=True, shape="per-stage")) as b:
            built[name] = (set(b.build_options()), "float3 collide_meshes(" in b._source)  # collide_mesh.cl's
    assert not any(o.startswith(("-DCLOTH_MESH", "-DCLOTH_PER_STEP", "-DCLOTH_ATTACHED")) for o in built["curtain"][0])
    assert not built["curtain"][1] and built["torus"][1] and built["sweep"][1] and not built["carried"][1]
    assert "-DCLOTH_MESHES=1" in built["torus"][0] and "-DCLOTH_PER_STEP" not in built["torus"][0]  # static: no motion
    assert {"-DCLOTH_MESHES=1", "-DCLOTH_PER_STEP"} <= built["sweep"][0]
    assert {"-DCLOTH_PER_STEP", "-DCLOTH_ATTACHED_PINS"} <= built["carried"][0]
