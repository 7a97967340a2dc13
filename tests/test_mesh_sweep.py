"""Mesh size, mesh algorithm and motion as sweep dimensions: the options and their
one-line refusals, the triangle count a built-in shape is set to, the rows a sweep writes, the
backends a scene is refused by (skipped with the reason, never a failed row), the mesh figure,
and mesh colliders in `clothbench render`."""

from __future__ import annotations

import csv
import sys
import types

import numpy as np
import pytest

from clothbench.backends import BACKENDS, Availability, Capabilities, availability, capabilities
from clothbench.backends.base import MESH_COLLISIONS
from clothbench.backends.numpy.verlet import NumpyBackend
from clothbench.cli import main
from clothbench.model.colliders.mesh import mesh_geometry
from clothbench.harness.plan import (
    scene_variants,
    shape_triangles,
    subdivisions_for,
    with_mesh_triangles,
    without_motion,
)
from clothbench.harness.sweep import SweepSettings, plan_sweep, run_sweep
from clothbench.model.scene import load_setup

from conftest import VERLET, require
from test_sweep import fake_entry


def tiny(name: str, grid: int = 6):
    return load_setup(name).replace(grid=grid)


# --- the options -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv, message",
    [
        (["sweep", "--scene", "sphere", "--mesh-collision", "naive"], "scene sphere has no [[mesh]] collider"),
        (["sweep", "--scene", "torus", "--mesh-collision", "fastest"], "--mesh-collision takes naive, accelerated"),
        (["sweep", "--scene", "sphere", "--mesh-triangles", "20"], "has no [[mesh]] collider to subdivide"),
        (["sweep", "--scene", "torus", "--mesh-triangles", "0"], "--mesh-triangles must all be >= 1"),
        (["sweep", "--scene", "torus", "--motion", "off"], "nothing to stop"),
        (["sweep", "--scene", "sweep", "--motion", "sideways"], "--motion takes on, off"),
        (["run", "--scene", "sphere", "--mesh-collision", "naive"], "scene sphere has no [[mesh]] collider"),
        (["run", "--scene", "torus", "--mesh-collision", "fastest"], "invalid choice: 'fastest'"),
    ],
)
def test_bad_mesh_options_are_one_line_and_exit_2(argv, message, tmp_path, capsys):
    assert main(argv + (["--out", str(tmp_path / "x.csv")] if argv[0] == "sweep" else [])) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert message in err
    assert not (tmp_path / "x.csv").exists(), "refused before any file is written"


def test_run_refuses_an_algorithm_its_backend_lacks_in_one_line(capsys):
    lacking = [a for a in MESH_COLLISIONS if a not in capabilities("numpy").mesh_collisions]
    if not lacking:
        pytest.skip("numpy has every mesh algorithm: nothing to refuse")
    assert main(["run", "--scene", "torus", "--grid", "6", "--steps", "1", "--mesh-collision", lacking[0]]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"numpy does not take --mesh-collision {lacking[0]}" in err


def test_a_file_mesh_is_refused_by_mesh_triangles_in_one_line(tmp_path, capsys):
    (tmp_path / "tetra.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    scene = tmp_path / "tetra.toml"
    scene.write_text('[cloth]\ngrid = 8\n[[mesh]]\nfile = "tetra.obj"\nposition = [0.5, 0.2, 0.5]\nscale = 0.2\n')
    out = tmp_path / "x.csv"
    assert main(["sweep", "--scene", str(scene), "--mesh-triangles", "20", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "reads its mesh from" in err and "tetra.obj" in err


# --- the triangle count ------------------------------------------------------------------


@pytest.mark.parametrize("shape, levels", [("box", 3), ("icosphere", 3), ("torus", 2)])
def test_each_level_has_the_triangles_the_formula_says_and_maps_back_to_itself(shape, levels):
    for s in range(levels):
        made = mesh_geometry(None, shape, s, (1.0, 1.0, 1.0)).triangles  # as the step sees them
        assert shape_triangles(shape, s) == made, f"{shape} at subdivisions {s}"
        assert subdivisions_for(shape, made) == s


@pytest.mark.parametrize(
    "shape, asked, level",
    [
        ("icosphere", 20, 0), ("icosphere", 300, 2), ("icosphere", 5000, 4), ("icosphere", 20480, 5),
        ("torus", 20, 0), ("torus", 20480, 3),  # 16,384 is 1.25x off, 65,536 3.2x
        ("box", 20000, 5),  # 12,288 is 1.6x off, 49,152 2.5x: nearest by ratio
        ("icosphere", 10**9, 6),  # never past the most Mesh.check takes
    ],
)  # fmt: skip
def test_a_count_goes_to_the_nearest_level_by_ratio(shape, asked, level):
    assert subdivisions_for(shape, asked) == level


def test_counts_nearest_one_level_are_one_row_and_the_move_is_said():
    scene = tiny("torus").scene
    assert with_mesh_triangles(scene, 4096).meshes[0].subdivisions == 2
    variants = scene_variants(scene, (20, 256, 1000))  # 20 and 256 are both 256 triangles
    assert [v.mesh_triangles for v, _, _ in variants] == [256, 1024]
    notes = [n for _, _, ns in variants for n in ns]
    assert any("--mesh-triangles 20: 256 triangles" in n for n in notes)
    assert any("--mesh-triangles 1000: 1024 triangles" in n for n in notes)


def test_motion_off_fixes_every_collider_and_every_attached_pin():
    scene = tiny("carried").scene
    still = without_motion(scene)
    assert scene.has_motion and not still.has_motion
    assert still.cylinders[0].start == scene.cylinders[0].start and still.pin_edge == scene.pin_edge
    assert [v.motion for v, _, _ in scene_variants(scene, motion=("on", "off"))] == ["on", "off"]


# --- the sweep ---------------------------------------------------------------------------


class FixedCollidersOnly(NumpyBackend):
    """The numpy step, declaring no meshes and no motion: what a kernel without them says."""

    name = "fake-fixed"
    capabilities = Capabilities()


class BothAlgorithms(NumpyBackend):
    """The numpy step, declaring both mesh algorithms (numpy's loop gives the same bits)."""

    name = "fake-both"
    capabilities = Capabilities(meshes=("verlet",), moving_colliders=("verlet",), mesh_collisions=MESH_COLLISIONS)


@pytest.fixture
def fakes(monkeypatch):
    usable = types.ModuleType("clothbench.backends._fake_mesh")
    usable.probe = lambda: Availability(True, device="fake device")
    monkeypatch.setitem(sys.modules, usable.__name__, usable)
    for cls in (FixedCollidersOnly, BothAlgorithms):
        setattr(usable, cls.__name__, cls)
        monkeypatch.setitem(BACKENDS, cls.name, fake_entry(cls.name, f"{usable.__name__}:{cls.__name__}"))
    availability.cache_clear()
    yield
    availability.cache_clear()


def settings_for(name: str, **dimensions) -> SweepSettings:
    return SweepSettings(
        setup=load_setup(name), grids=[6], steps=2, repeats=2, isolate=False, bounds=False, **dimensions
    )


def test_a_backend_that_refuses_the_scene_is_skipped_with_its_refusal_not_failed(tmp_path, fakes):
    settings = settings_for("torus")
    seen = []
    progress = run_sweep(["numpy", "fake-fixed"], settings, tmp_path / "s.csv", on_start=seen.append)
    skipped = dict(seen[0].plan.skipped)
    assert "fake-fixed does not take mesh colliders" in skipped["fake-fixed"]
    assert {r["backend"] for r in progress.measured} == {"numpy"}
    assert all(r["status"] == "ok" for r in progress.measured)


def test_each_mesh_algorithm_is_a_row_where_the_backend_has_it_and_skipped_where_not(fakes):
    settings = settings_for("torus", mesh_collisions=MESH_COLLISIONS)
    scenes = [(sv, s) for sv, s, _ in settings.scene_variants]
    plan = plan_sweep(["numpy", "fake-both"], [6], [VERLET], scenes=scenes, mesh_collisions=MESH_COLLISIONS)
    by_backend: dict[str, set] = {}
    for row in plan.rows:
        by_backend.setdefault(row.backend, set()).add(row.options.mesh_collision)
    assert by_backend["fake-both"] == set(MESH_COLLISIONS)
    assert by_backend["numpy"] == set(capabilities("numpy").mesh_collisions)
    for a in set(MESH_COLLISIONS) - set(capabilities("numpy").mesh_collisions):
        assert f"numpy does not take --mesh-collision {a}" in dict(plan.skipped)[f"numpy mesh={a}"]
    assert all(f"mesh={r.options.mesh_collision}" in r.variant.label for r in plan.rows)


def test_a_tiny_sweep_writes_a_row_per_triangle_count_with_the_columns_filled(tmp_path):
    out = tmp_path / "mesh.csv"
    progress = run_sweep(["numpy"], settings_for("torus", mesh_triangles=(256, 1024)), out)
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 4 and all(r["status"] == "ok" for r in rows)  # f64 and f32 at each count
    assert sorted(r["mesh_triangles"] for r in rows) == ["1024", "1024", "256", "256"]
    default = capabilities("numpy").mesh_collisions[0]
    assert all(r["mesh_collision"] == default and r["mode"].endswith(f"/mesh={default}") for r in rows)
    assert all(r["motion"] == "" for r in rows), "the torus has no motion"
    # the f32 rows are checked against the f64 run of their own mesh: an error near float32's
    assert all(float(r["err_rms_m"]) < 1e-5 for r in rows)
    assert len(progress.measured) == 4


def test_motion_on_and_off_are_rows_of_their_own(tmp_path):
    out = tmp_path / "motion.csv"
    run_sweep(["numpy"], settings_for("carried", motion=("on", "off")), out)
    rows = [r for r in csv.DictReader(out.open()) if r["precision"] == "f32"]
    assert sorted(r["motion"] for r in rows) == ["off", "on"] and all(r["status"] == "ok" for r in rows)


# --- the figure --------------------------------------------------------------------------


def test_the_crossover_is_where_accelerated_starts_to_stay_faster():
    from clothbench.reports.plots import crossover

    naive = [(20, 1.0), (320, 2.0), (5120, 32.0), (20480, 128.0)]
    accelerated = [(20, 2.0), (320, 3.0), (5120, 4.0), (20480, 5.0)]
    kind, at = crossover(naive, accelerated)
    assert kind == "between" and 320 < at < 5120
    assert crossover(naive, [(t, ms / 2) for t, ms in naive]) == ("always", None)
    assert crossover(naive, [(t, ms * 2) for t, ms in naive]) == ("never", None)


def test_the_mesh_figure_draws_a_line_per_backend_and_algorithm(tmp_path, capsys):
    out = tmp_path / "mesh.csv"
    run_sweep(["numpy"], settings_for("torus", mesh_triangles=(256, 1024)), out)
    assert main(["plot", str(out), "--kind", "mesh", "--out", str(tmp_path / "mesh.png")]) == 0
    assert (tmp_path / "mesh.png").stat().st_size > 10_000 and (tmp_path / "mesh.svg").exists()
    printed = capsys.readouterr().out
    assert "mesh_triangles:" in printed  # the crossover, or why there is none
    from clothbench.reports.plots import draw_sweep

    report = draw_sweep(out)
    assert sorted(report.series["mesh_triangles"]) == sorted(
        f"CPU (numpy) {p}, {capabilities('numpy').mesh_collisions[0]}" for p in ("f32", "f64")
    )


def test_a_csv_without_triangle_counts_is_refused_by_the_mesh_figure_in_one_line(tmp_path, capsys):
    out = tmp_path / "one.csv"
    run_sweep(["numpy"], settings_for("torus"), out)
    assert main(["plot", str(out), "--kind", "mesh"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fewer than two triangle counts" in err


# --- render ------------------------------------------------------------------------------


def render_image(tmp_path, scene, steps: int = 20):
    from PIL import Image

    from clothbench.backends import BackendOptions
    from clothbench.reports.render import RenderSettings, render

    out = tmp_path / f"{len(scene.meshes)}.png"
    render(scene, VERLET, "numpy", BackendOptions(), RenderSettings(frames=1, every=steps, size=(160, 120)), str(out))
    return np.asarray(Image.open(out).convert("RGB")).astype(int)


def is_collider(pixels: np.ndarray) -> np.ndarray:
    return pixels[..., 2] > pixels[..., 0] + 30  # blue: the colliders' colour


def test_a_mesh_collider_is_drawn(tmp_path):
    require("glsl")  # a GL context to draw in, whichever backend steps
    scene = tiny("torus", 12).scene
    with_mesh = render_image(tmp_path, scene)
    without = render_image(tmp_path, scene.replace(meshes=()))  # the same camera: the torus is in its box
    assert is_collider(with_mesh).sum() > 200 + is_collider(without).sum(), "the torus shows as collider pixels"


def test_a_moving_collider_is_drawn_where_it_is_at_the_frames_time(tmp_path):
    require("glsl")
    from clothbench.backends.gl import context as gl_context
    from clothbench.harness.normals import grid_normals
    from clothbench.reports.render import Renderer

    scene = tiny("sweep", 12).scene  # the paddle turns 90 degrees a second about the vertical
    pos, _ = scene.initial_state(np.float32)
    renderer = Renderer(gl_context.get_device("egl"), scene, (160, 120), duration=1.0)
    try:
        frames = []
        for t in (0.0, 1.0):  # a quarter turn apart
            renderer.time = t
            frames.append(is_collider(renderer.draw_arrays(pos, grid_normals(pos, scene.grid, np.float32)).astype(int)))
    finally:
        renderer.close()
    assert frames[0].sum() > 20 and frames[1].sum() > 20
    assert (frames[0] != frames[1]).mean() > 0.005, "the paddle is drawn turned"


def test_render_steps_on_numpy_where_glsl_refuses_the_scene(capsys):
    from clothbench.cli.render import default_backend

    scene = tiny("torus").scene
    expected = "glsl" if capabilities("glsl").scene_refusal("glsl", scene) is None else "numpy"
    assert default_backend(scene, "verlet") == expected
    assert default_backend(tiny("sphere").scene, "verlet") == "glsl"
    if expected == "numpy":
        assert "stepped on numpy" in capsys.readouterr().err
