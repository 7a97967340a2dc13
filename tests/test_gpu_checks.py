"""The GPU checks that no other test file makes: each runs only on an NVIDIA GPU
(tools/gpu-check runs them there) and skips elsewhere with the reason.

- CUDA strict after 1 and 500 steps on every built-in scene in the copy transfer mode (the
  contract, tests/contract/test_verlet_contract.py, runs the default swap mode);
- GL fragment and compute on the NVIDIA driver, not a CPU rasteriser that EGL fell back to;
- OpenCL strict and PBD on the NVIDIA ICD itself, whichever device is the default.

Strict means bit for bit with the NumPy float32 reference (docs/semantics.md), so these
tests have no tolerance.
"""

from __future__ import annotations

import shutil
import subprocess
from functools import lru_cache

import numpy as np
import pytest

from clothbench.backends import BackendOptions, availability, capabilities
from clothbench.harness import reference, simulate
from clothbench.scene import builtin_scenes, load_scene
from clothbench.solver import Pbd

from conftest import VERLET, assert_bit_exact, every_collider_scene, require, setup

SCENES = (*builtin_scenes(), "all-kinds")
N = 32  # every collider touched within 500 steps (tests/test_colliders.py)


@lru_cache(maxsize=1)
def nvidia_gpu() -> str:
    """The first GPU nvidia-smi lists, or "" where there is none."""
    if shutil.which("nvidia-smi") is None:
        return ""
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True, timeout=30
        )
    except (OSError, subprocess.TimeoutExpired):
        return ""
    names = [line.strip() for line in out.stdout.splitlines() if line.strip()] if out.returncode == 0 else []
    return names[0] if names else ""


def require_nvidia_gpu() -> str:
    name = nvidia_gpu()
    if not name:
        pytest.skip("no NVIDIA GPU: nvidia-smi is not here or lists none")
    return name


def scene_named(name: str, n: int = N):
    return every_collider_scene(n) if name == "all-kinds" else load_scene(name).replace(grid=n)


@pytest.mark.parametrize("steps", [1, 500])  # 500: after contact with every collider
@pytest.mark.parametrize("scene_name", SCENES)
def test_cuda_strict_in_copy_mode_matches_numpy_f32_bit_for_bit(scene_name, steps):
    require("cuda")
    assert "copy" in capabilities("cuda").transfers
    scene = scene_named(scene_name)
    refusal = capabilities("cuda").scene_refusal("cuda", scene)
    if refusal:  # a scene the cuda backend does not take yet ([self_collision])
        pytest.skip(refusal)
    pos, prev = simulate("cuda", scene, VERLET, steps, BackendOptions(strict=True, transfer="copy"))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    assert_bit_exact(pos, ref_pos, f"pos, cuda copy {scene_name} steps={steps}")
    assert_bit_exact(prev, ref_prev, f"prev, cuda copy {scene_name} steps={steps}")


@pytest.mark.parametrize("backend", ["glsl", "glsl-compute"])
def test_gl_runs_on_the_nvidia_driver_where_there_is_an_nvidia_gpu(backend):
    # EGL falls back to Mesa's llvmpipe when it finds no NVIDIA vendor library: the GL rows
    # would then time a CPU and call it the GPU (tools/gpu-check names the vendor file)
    gpu = require_nvidia_gpu()
    a = availability(backend)
    assert a.usable, f"{backend} cannot run on this {gpu}: {a.reason}"
    assert "nvidia" in a.device.lower() and "llvmpipe" not in a.device.lower(), f"{backend} runs on {a.device!r}"


def nvidia_opencl_device() -> str:
    """The 'platform:device' of the first NVIDIA OpenCL device; skips where there is none."""
    require_nvidia_gpu()
    require("opencl")
    from clothbench.backends.opencl.device import ordered_devices

    for spec, device, _ in ordered_devices():
        if "nvidia" in f"{device.platform.name} {device.platform.vendor}".lower():
            return spec
    pytest.skip("no NVIDIA OpenCL platform: NVIDIA's ICD is not registered (tools/gpu-check registers it)")


@pytest.mark.parametrize("steps", [1, 500])
@pytest.mark.parametrize("scene_name", ["sphere", "all-kinds"])
def test_opencl_strict_on_the_nvidia_icd_matches_numpy_f32_bit_for_bit(scene_name, steps):
    spec = nvidia_opencl_device()
    scene = scene_named(scene_name)
    pos, prev = simulate("opencl", scene, VERLET, steps, BackendOptions(strict=True, device=spec))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    assert_bit_exact(pos, ref_pos, f"pos, opencl {spec} {scene_name} steps={steps}")
    assert_bit_exact(prev, ref_prev, f"prev, opencl {spec} {scene_name} steps={steps}")


@pytest.mark.parametrize("method", ["jacobi", "coloured"])
def test_opencl_pbd_strict_on_the_nvidia_icd_matches_numpy_f32_bit_for_bit(method):
    # the curtain swinging onto its sphere at 60 Hz, as tests/test_pbd_gpu.py runs it on the default device
    spec = nvidia_opencl_device()
    s = setup("curtain", 24).replace(solver="pbd", method=method, iterations=10, dt=1 / 60)
    assert isinstance(s.solver, Pbd)
    pos, _ = simulate("opencl", s.scene, s.solver, 60, BackendOptions(strict=True, device=spec))
    want, _ = simulate("numpy", s.scene, s.solver, 60, BackendOptions(precision="f32"))
    assert np.isfinite(pos).all()
    assert_bit_exact(pos, want, f"pos, opencl {spec} pbd-{method}")
