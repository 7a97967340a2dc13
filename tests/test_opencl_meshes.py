"""Meshes, moving colliders and pins attached to a body on the OpenCL Verlet backend
(kernels/collide_mesh.cl, docs/semantics.md "Triangle mesh", "Moving colliders", "Pins
attached to a body"), what is OpenCL's own: a moving scene offers the multi-step shape, and a
scene compiles only the parts it has. The contract (strict bits with either search, in every
shape and build; the bodies' clock; fast error; the searches agreeing) is
tests/contract/test_bodies_contract.py."""

from __future__ import annotations

import functools

import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.opencl import verlet as opencl
from clothbench.scene import load_setup
from conftest import require

N = 32  # the contract's grid
ALGORITHMS = ("naive", "accelerated")


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


@functools.lru_cache(maxsize=None)
def setup(name: str, n: int = N):
    s = load_setup(name)
    return s.scene.replace(grid=n), s.solver


def strict(algorithm: str, **values) -> BackendOptions:
    return BackendOptions(strict=True, mesh_collision=algorithm, **values)


# --- the multi-step shape ---------------------------------------------------------------------


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("name", ["sweep", "carried"])
def test_a_moving_scene_offers_the_multistep_shape(name, algorithm):
    # it reads one table of poses per step of its launch; the contract runs every shape offered
    # (tests/contract/test_bodies_contract.py), so this says the multi-step one is among them
    scene, _ = setup(name)
    shapes = opencl.OpenCLBackend.kernel_shapes(scene, strict(algorithm))
    assert any(s.startswith("steps/") for s in shapes), shapes


# --- what is compiled -------------------------------------------------------------------------


def program_sources(backend) -> str:
    """The source build_program handed the compiler for each of the backend's programs. Not
    the program's own SOURCE: on Intel's runtime a program pyopencl's binary cache serves is
    made from the binary, and its source is empty (PoCL's is always built from source)."""
    from clothbench.backends.opencl.device import _programs

    sources = [source for (_, source, _), program in _programs.items() if any(program is p for p in backend.programs)]
    assert len(sources) == len({id(p) for p in backend.programs}), "every program is in the program cache"
    return "".join(sources)


@pytest.mark.parametrize("generic", [False, True])
def test_a_scene_without_meshes_or_motion_compiles_none_of_it(generic):
    scene, solver = setup("drape")
    with create_backend("opencl", scene, solver, BackendOptions(strict=True, generic=generic)) as b:
        source, options = program_sources(b), " ".join(o for key in b.key for o in key)
    assert "closest_point" not in source and "collide_mesh(" not in source, "mesh code in the source"
    for option in ("CLOTH_MESHES", "CLOTH_MESH_BVH", "CLOTH_PER_STEP", "CLOTH_ATTACHED_PINS"):
        assert option not in options


def test_a_static_mesh_scene_compiles_its_search_and_no_motion():
    scene, solver = setup("torus")
    for algorithm in ALGORITHMS:
        with create_backend("opencl", scene, solver, strict(algorithm)) as b:
            source, options = program_sources(b), " ".join(o for key in b.key for o in key)
        assert "closest_point" in source and "-DCLOTH_MESHES=1" in options
        assert ("-DCLOTH_MESH_BVH" in options) == (algorithm == "accelerated")
        assert "CLOTH_PER_STEP" not in options and "CLOTH_ATTACHED_PINS" not in options
