"""`clothbench run --export`: the run's frames in USD (read with OpenUSD's own library, pxr)
and as OBJ or PLY files (read with trimesh), each frame the state `run --save` writes after
that many steps, and `render --from` / `view --from` reading a USD back.

Tolerances: a USD's points and a PLY's vertices are float32 as the state is, so they are
compared bit for bit; an OBJ is text with OBJ_DIGITS decimal places, so its vertices are within
half a unit of the last place (OBJ_TOLERANCE), the rounding of that printing.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from clothbench import cli
from clothbench.harness.normals import grid_normals
from clothbench.reports.export import OBJ_TOLERANCE, RunInfo, UsdWriter, frame_steps, read_usd
from clothbench.reports.meshes import cloth_indices
from clothbench.model.scene import body_pose, load_setup

from conftest import BOX_SCENE, assert_bit_exact, require

pxr = pytest.importorskip("pxr", reason="usd-core not installed (pip install 'clothbench[export]')")
from pxr import Usd, UsdGeom  # noqa: E402

N = 12
DT = load_setup("sphere").solver.dt


def run(tmp_path, *args, scene="sphere", steps=45) -> None:
    argv = ["run", "--scene", scene, "--grid", str(N), "--steps", str(steps), "--json", *args]
    assert cli.main(argv) == 0


def saved(path) -> np.ndarray:
    with np.load(path) as state:
        return state["pos"]


def cloth_points(stage, code) -> np.ndarray:
    return np.array(UsdGeom.Mesh.Get(stage, "/World/Cloth").GetPointsAttr().Get(code), dtype=np.float32)


def test_the_usd_has_a_frame_every_k_steps_and_the_last_step(tmp_path):
    out = tmp_path / "anim.usd"
    run(tmp_path, "--export", str(out), "--export-every", "10")
    stage = Usd.Stage.Open(str(out))
    cloth = UsdGeom.Mesh.Get(stage, "/World/Cloth")
    # steps 0, 10, 20, 30, 40 and 45: one time code per exported frame, the last one half a frame on
    assert cloth.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0, 4.5]
    assert cloth.GetNormalsAttr().GetTimeSamples() == cloth.GetExtentAttr().GetTimeSamples() == [0, 1, 2, 3, 4, 4.5]
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 4.5)
    assert stage.GetTimeCodesPerSecond() == pytest.approx(1 / (10 * DT))  # a time code is 10 steps of dt
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/World"
    triangles = cloth_indices(N)
    assert list(cloth.GetFaceVertexCountsAttr().Get()) == [3] * len(triangles) == [3] * 2 * (N - 1) ** 2
    assert np.array_equal(np.array(cloth.GetFaceVertexIndicesAttr().Get()), triangles.reshape(-1))
    assert cloth.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none  # drawn as triangles, not a limit surface
    assert cloth.GetOrientationAttr().Get() == UsdGeom.Tokens.rightHanded
    assert stage.GetPrimAtPath("/World/Colliders/sphere_0").IsA(UsdGeom.Sphere)


def test_each_frame_is_the_state_run_save_writes_at_that_step_bit_for_bit(tmp_path):
    out, final = tmp_path / "anim.usd", tmp_path / "final.npz"
    run(tmp_path, "--export", str(out), "--export-every", "10", "--save", str(final))
    stage = Usd.Stage.Open(str(out))
    assert_bit_exact(cloth_points(stage, 4.5), saved(final)[:, :3], "the last frame against the run's --save")
    for steps, code in ((10, 1.0), (30, 3.0)):
        at = tmp_path / f"at{steps}.npz"
        run(tmp_path, "--save", str(at), steps=steps)
        assert_bit_exact(cloth_points(stage, code), saved(at)[:, :3], f"frame {code} against run --steps {steps}")
    start = load_setup("sphere").replace(grid=N).scene.initial_state(np.float32)[0]
    assert_bit_exact(cloth_points(stage, 0.0), start[:, :3], "frame 0 against the initial state")


def test_normals_and_bounds_are_those_of_each_frame_s_points(tmp_path):
    out = tmp_path / "anim.usda"  # the text format: the same stage
    run(tmp_path, "--export", str(out), "--export-every", "15", steps=300)
    stage = Usd.Stage.Open(str(out))
    cloth = UsdGeom.Mesh.Get(stage, "/World/Cloth")
    for code in cloth.GetPointsAttr().GetTimeSamples():
        points = cloth_points(stage, code)
        normals = np.array(cloth.GetNormalsAttr().Get(code), dtype=np.float32)
        assert_bit_exact(normals, grid_normals(points, N, np.float32), f"the normals of frame {code}")
        lo, hi = points.min(axis=0), points.max(axis=0)
        assert np.array_equal(np.array(cloth.GetExtentAttr().Get(code)), np.stack([lo, hi]))
        box = UsdGeom.BBoxCache(Usd.TimeCode(code), [UsdGeom.Tokens.default_]).ComputeWorldBound(cloth.GetPrim())
        r = box.ComputeAlignedRange()
        assert np.allclose(np.array(r.GetMin()), lo) and np.allclose(np.array(r.GetMax()), hi)
    assert np.allclose(np.array(cloth.GetNormalsAttr().Get(0.0)), (0.0, 1.0, 0.0))  # the flat sheet faces up
    assert cloth_points(stage, 20.0)[:, 1].min() < cloth_points(stage, 0.0)[:, 1].min() - 0.01, "the cloth falls"
    sphere = load_setup("sphere").scene.spheres[0]
    prim = stage.GetPrimAtPath("/World/Colliders/sphere_0")
    r = UsdGeom.BBoxCache(Usd.TimeCode(0), [UsdGeom.Tokens.default_]).ComputeWorldBound(prim).ComputeAlignedRange()
    assert np.allclose(np.array(r.GetMin()), np.array(sphere.center) - sphere.radius)
    assert np.allclose(np.array(r.GetMax()), np.array(sphere.center) + sphere.radius)


def test_a_moving_collider_is_time_sampled_at_its_pose_and_a_still_one_is_not(tmp_path):
    out = tmp_path / "sweep.usd"
    run(tmp_path, "--export", str(out), "--export-every", "20", scene="sweep", steps=100)
    stage = Usd.Stage.Open(str(out))
    paddle = load_setup("sweep").scene.meshes[0]
    xform = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Colliders/mesh_0"))
    assert xform.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    for code in (0.0, 3.0, 5.0):
        rotation, translation = body_pose(paddle, code * 20 * DT)  # the pose at the end of the frame's last step
        m = np.array(xform.ComputeLocalToWorldTransform(Usd.TimeCode(code))).T  # USD's row vectors, transposed
        assert np.allclose(m[:3, :3], rotation, atol=1e-12) and np.allclose(m[:3, 3], translation, atol=1e-12)
    assert not np.allclose(*(np.array(xform.ComputeLocalToWorldTransform(Usd.TimeCode(c))) for c in (0.0, 5.0)))
    for prim in stage.GetPrimAtPath("/World/Colliders").GetChildren():
        if prim.GetName() != "mesh_0":
            assert not UsdGeom.Xformable(prim).GetTimeSamples(), f"{prim.GetName()} does not move"


def test_a_box_is_a_cube_prim_where_the_box_is_and_a_moving_one_follows_its_pose(tmp_path):
    out = tmp_path / "boxes.usd"
    scene_file = str(BOX_SCENE)
    run(tmp_path, "--export", str(out), "--export-every", "10", scene=scene_file, steps=20)
    stage = Usd.Stage.Open(str(out))
    for i, box in enumerate(load_setup(scene_file).scene.boxes):
        prim = stage.GetPrimAtPath(f"/World/Colliders/box_{i}")
        assert prim.IsA(UsdGeom.Cube), box.name
        for code in (0.0, 2.0):
            rotation, centre = body_pose(box, code * 10 * DT)
            corners = np.array(
                [centre + rotation @ ((2 * np.array(c) - 1) * box.half_extents) for c in np.ndindex(2, 2, 2)]
            )
            cache = UsdGeom.BBoxCache(Usd.TimeCode(code), [UsdGeom.Tokens.default_])
            r = cache.ComputeWorldBound(prim).ComputeAlignedRange()
            assert np.allclose(np.array(r.GetMin()), corners.min(axis=0), atol=1e-9), (box.name, code)
            assert np.allclose(np.array(r.GetMax()), corners.max(axis=0), atol=1e-9), (box.name, code)
        assert bool(UsdGeom.Xformable(prim).GetTimeSamples()) == (box.motion is not None), box.name


def test_a_200_frame_64_squared_run_is_under_20_mb(tmp_path):
    # the writer as `run --export` drives it, without the simulation: the size depends on the
    # counts of points and frames, not on their values (float32 in the crate format, uncompressed);
    # docs/export.md gives the size of a real run's file
    setup = load_setup("sphere").replace(grid=64)
    every, steps = 10, 1990  # frames at steps 0, 10, ..., 1990: 200 of them
    out = tmp_path / "anim.usd"
    info = RunInfo("sphere", 64, setup.solver.dt, setup.solver.spec, every, steps, "numpy", "f32")
    writer = UsdWriter(out, setup.scene, info)
    pos = setup.scene.initial_state(np.float32)[0]
    rng = np.random.default_rng(0)
    for step in frame_steps(steps, every):
        writer.frame(step, pos + rng.normal(0, 0.01, pos.shape).astype(np.float32))
    writer.close()
    assert len(Usd.Stage.Open(str(out)).GetPrimAtPath("/World/Cloth").GetAttribute("points").GetTimeSamples()) == 200
    assert out.stat().st_size < 20e6


@pytest.mark.parametrize("kind", ["obj", "ply"])
def test_a_folder_gets_a_mesh_per_frame_with_the_state_s_vertices(tmp_path, kind):
    import trimesh

    out, final = tmp_path / "frames", tmp_path / "final.npz"
    run(tmp_path, "--export", f"{out}/", "--export-every", "20", "--export-format", kind, "--save", str(final))
    files = sorted(out.iterdir())
    assert [f.name for f in files] == [f"frame_{i:04d}.{kind}" for i in range(4)]  # steps 0, 20, 40, 45
    mesh = trimesh.load(files[-1], process=False)
    assert len(mesh.vertices) == N * N and np.array_equal(mesh.faces, cloth_indices(N))
    state = saved(final)[:, :3]
    if kind == "ply":  # binary: the float32 values themselves
        assert_bit_exact(np.asarray(mesh.vertices, dtype=np.float32), state, "the PLY's vertices")
    else:
        assert np.abs(mesh.vertices - state.astype(np.float64)).max() <= OBJ_TOLERANCE
    assert not np.allclose(trimesh.load(files[0], process=False).vertices, mesh.vertices), "the frames differ"


@pytest.mark.parametrize(
    "args, message",
    [
        (["--export", "{tmp}/anim.abc"], "--export takes a .usd, .usda, .usdc file or a folder/"),
        (["--export-every", "5"], "--export-every applies to --export only"),
        (["--export-format", "ply"], "--export-format applies to --export only"),
        (["--export", "{tmp}/anim.usd", "--export-every", "0"], "--export-every must be >= 1"),
        (["--export", "{tmp}/anim.usd/"], "is a folder with a .usd suffix"),
        (["--export", "{tmp}/no/such/anim.usd"], "there is no folder"),
        (["--export", "{tmp}/no/such/frames/"], "there is no folder"),
        (["--export", "{tmp}/anim.usd", "--export-format", "obj"], "--export-format chooses the files of a folder"),
    ],
)
def test_bad_export_options_are_one_line_before_any_work(tmp_path, capsys, args, message):
    args = [a.format(tmp=tmp_path) for a in args]
    assert cli.main(["run", "--grid", "8", "--steps", "5", *args]) == 2
    out, err = capsys.readouterr()
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert out == "" and not any(tmp_path.iterdir()), "refused before the run, nothing written"


def test_a_folder_holding_an_earlier_exports_frames_is_refused_before_the_run(tmp_path, capsys):
    # a shorter export over a longer one would leave the old last frames beside the new ones
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "frame_0007.ply").write_text("an earlier run's frame")
    (frames / "notes.txt").write_text("not a frame: no reason to refuse")
    assert cli.main(["run", "--grid", "8", "--steps", "5", "--export", f"{frames}/"]) == 2
    out, err = capsys.readouterr()
    assert "already holds 1 frame file (frame_0007.ply ...) from an earlier export" in err and "remove them" in err, err
    assert len(err.strip().splitlines()) == 1 and out == ""
    assert sorted(p.name for p in frames.iterdir()) == ["frame_0007.ply", "notes.txt"], "nothing removed"
    (frames / "frame_0007.ply").unlink()
    assert cli.main(["run", "--grid", "8", "--steps", "5", "--export", f"{frames}/", "--export-every", "5"]) == 0
    assert sorted(p.name for p in frames.glob("frame_*")) == ["frame_0000.obj", "frame_0001.obj"]


def test_without_usd_core_a_usd_export_names_the_package_before_the_run(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pxr.UsdGeom", None)  # as if it were not installed: import fails
    assert cli.main(["run", "--grid", "8", "--steps", "5", "--export", str(tmp_path / "a.usd")]) == 2
    out, err = capsys.readouterr()
    assert "pip install usd-core" in err and len(err.strip().splitlines()) == 1 and out == ""


def test_an_export_says_where_and_that_it_was_read_back_untimed(tmp_path, capsys):
    out = tmp_path / "anim.usd"
    assert cli.main(["run", "--grid", "8", "--steps", "30", "--export", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert f"exported 4 frames to {out} (every 10 steps, read back in an untimed second run)" in stdout


@pytest.mark.serial  # holds a GL context
def test_render_from_draws_the_frame_where_its_cloth_projects(tmp_path):
    from PIL import Image

    from clothbench.reports.render import frame_scene

    require("glsl")  # the renderer's GL context
    out, png = tmp_path / "anim.usd", tmp_path / "frame.png"
    run(tmp_path, "--export", str(out), "--export-every", "50", steps=200)
    assert cli.main(["render", "--from", str(out), "--frame", "2", "--size", "160x120", "--out", str(png)]) == 0
    image = np.asarray(Image.open(png).convert("RGB"))
    exported = read_usd(out)
    assert exported.step(2) == 100 and exported.frames == 5
    # the camera render --from frames its scene with, over the whole file's time
    camera = frame_scene(exported.scene, (160, 120), exported.time(exported.frames - 1))
    inner = exported.points[2].reshape(N, N, 3)[1:-1, 1:-1].reshape(-1, 3)
    col, row = np.round(camera.project(inner)).astype(int).T
    r, b = image[row, col, 0].astype(int), image[row, col, 2].astype(int)
    on_cloth = (r > 1.5 * b) & (r - b > 30)  # red or gold: test_render.py's cloth colours
    assert on_cloth.mean() > 0.95, f"only {on_cloth.mean():.0%} of the frame's particles fall on cloth pixels"
    gif = tmp_path / "all.gif"
    assert cli.main(["render", "--from", str(out), "--size", "64x48", "--out", str(gif)]) == 0
    with Image.open(gif) as animation:
        assert animation.n_frames == 5


@pytest.mark.parametrize(
    "args, message",
    [
        (["--frame", "9"], "--frame 9: {usd} has frames 0 to 4"),
        (["--grid", "16"], "--grid sets up a simulation, and --from draws the file's frames"),
        (["--backend", "numpy"], "--backend sets up a simulation"),
        (["--out", "{tmp}/x.gif", "--frame", "1"], "--frame draws one frame into a .png"),
    ],
)
def test_render_from_refuses_what_does_not_apply_in_one_line(tmp_path, capsys, args, message):
    usd = tmp_path / "anim.usd"
    run(tmp_path, "--export", str(usd), "--export-every", "50", steps=200)
    capsys.readouterr()
    args = [a.format(tmp=tmp_path) for a in args]
    out = [] if "--out" in args else ["--out", str(tmp_path / "x.png")]
    assert cli.main(["render", "--from", str(usd), *out, *args]) == 2
    err = capsys.readouterr().err
    assert message.format(usd=usd) in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim.usd"]


def test_render_and_view_refuse_a_file_that_is_not_an_export(tmp_path, capsys):
    other = tmp_path / "other.usda"
    stage = Usd.Stage.CreateNew(str(other))
    UsdGeom.Xform.Define(stage, "/World")
    stage.Save()
    assert cli.main(["render", "--from", str(other), "--out", str(tmp_path / "x.png")]) == 2
    assert "not a file `clothbench run --export` wrote" in capsys.readouterr().err
    assert cli.main(["render", "--from", str(tmp_path / "x.obj"), "--out", str(tmp_path / "x.png")]) == 2
    assert "--from takes a USD file" in capsys.readouterr().err


@pytest.mark.serial  # holds a GL context (a window)
def test_view_from_plays_the_file_s_frames_one_a_viewer_frame(tmp_path):
    pytest.importorskip("moderngl_window", reason="moderngl-window not installed (pip install moderngl-window)")
    require("glsl")  # the headless window is an EGL context
    usd, log, state = tmp_path / "anim.usd", tmp_path / "log.jsonl", tmp_path / "state.npz"
    run(tmp_path, "--export", str(usd), "--export-every", "10", steps=100)
    argv = ["view", "--from", str(usd), "--headless", "--frames", "6", "--size", "160x120", "--keys", "3:F3",
            "--log", str(log), "--save", str(state)]  # fmt: skip
    assert cli.main(argv) == 0
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert [line["step"] for line in lines] == [10, 20, 30, 40, 50, 60]  # the file's every, one frame each
    assert {line["backend"] for line in lines} == {"usd"}
    assert any("a playback's frames are the file's" in e for e in lines[2]["events"]), "F3 switches nothing"
    assert_bit_exact(saved(state)[:, :3], read_usd(usd).points[6], "the last frame shown against the file's")
