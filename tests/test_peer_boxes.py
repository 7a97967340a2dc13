"""The oriented box on the peers that take it (Capabilities.boxes), held as tests/test_peers.py
holds their other colliders: strict is the NumPy float32 reference bit for bit
(tests/contract/test_box_contract.py, on every backend declaring boxes), and in either mode
no particle ends inside a box. The scene is the contract's (tests/data/boxes.toml) with its
motion stopped: no peer takes moving colliders."""

from __future__ import annotations


import numpy as np
import pytest

from clothbench.backends import BackendOptions, backend_class
from clothbench.harness import reference, simulate
from clothbench.harness.health import max_penetration
from clothbench.harness.plan import without_motion
from clothbench.model.scene import load_setup

from conftest import BOX_SCENE, BOX_STEPS, assert_bit_exact, require

PEERS = ("taichi", "warp", "numba", "torch", "jax")  # the CPU peers; cupy and numba-cuda need a GPU
# float32 rounding leaves a pushed-out particle a few ulp inside (tests/test_peers.py's bound)
PENETRATION_TOLERANCE = 1e-6


def box_peers() -> list[str]:
    return [name for name in PEERS if "verlet" in backend_class(name).capabilities.boxes]


def stopped_box_scene():
    setup = load_setup(str(BOX_SCENE))
    return without_motion(setup.scene), setup.solver


@pytest.mark.parametrize("strict", [False, True], ids=["fast", "strict"])
@pytest.mark.parametrize("name", box_peers())
def test_no_particle_ends_inside_a_box(name, strict):
    require(name)
    scene, solver = stopped_box_scene()
    pos = simulate(name, scene, solver, BOX_STEPS, BackendOptions(strict=strict))[0]
    assert np.isfinite(pos).all(), f"{name}: non-finite positions"
    without_boxes = reference(scene.replace(boxes=()), solver, BOX_STEPS, "f32")[0]
    assert max_penetration(without_boxes, scene) > 1e-2, "without its boxes the sheet passes through them"
    assert max_penetration(pos, scene) <= PENETRATION_TOLERANCE, f"{name} strict={strict}: a particle is inside"


def test_warp_default_with_boxes_is_numpy_f32_bit_for_bit():
    # Warp's default kernel is its strict one (clothbench/peers/warp.py), boxes included
    require("warp")
    scene, solver = stopped_box_scene()
    got, want = simulate("warp", scene, solver, BOX_STEPS), reference(scene, solver, BOX_STEPS, "f32")
    assert_bit_exact(got[0], want[0], "warp default, boxes, pos")
    assert_bit_exact(got[1], want[1], "warp default, boxes, prev")
