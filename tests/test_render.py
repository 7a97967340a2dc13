"""`clothbench render`: the cloth and its colliders drawn offscreen into PNGs and GIFs.

The pictures are checked by colour: the cloth's checker is red and gold (red well above
blue), the colliders blue, the background a pale blue-grey, the floor grey. The GL
backends draw from their own device state, never reading it back, and give the same
image as a backend whose positions are read back and uploaded.
"""

from __future__ import annotations


import numpy as np
import pytest
from PIL import Image

from clothbench import cli
from clothbench.backends import BackendOptions, capabilities
from clothbench.backends.gl import fragment as glsl
from clothbench.backends.gl import compute as glsl_compute
from clothbench.harness import simulate
from clothbench.reports import render as render_module
from clothbench.reports.meshes import cloth_indices, cube_mesh
from clothbench.reports.render import RenderSettings, frame_scene, render
from clothbench.model.scene import load_scene
from clothbench.model.solver import Pbd

from conftest import BOX_SCENE, VERLET, require

pytestmark = pytest.mark.serial  # holds a GL context: one xdist worker

SIZE = (160, 120)
# Strict GL and numpy f32 states are the same bits, so the two ways to the vertex shader
# draw the same triangles: at most a few edge pixels may differ (measured: none).
PIXEL_TOLERANCE = 0.002  # fraction of pixels allowed to differ


@pytest.fixture(autouse=True)
def gl():
    require("glsl")  # every render needs a GL context, whichever backend simulates


def is_cloth(pixels: np.ndarray) -> np.ndarray:
    """Red or gold, lit or in shade: red well above blue."""
    r, b = pixels[..., 0].astype(int), pixels[..., 2].astype(int)
    return (r > 1.5 * b) & (r - b > 30)


def is_collider(pixels: np.ndarray) -> np.ndarray:
    r, b = pixels[..., 0].astype(int), pixels[..., 2].astype(int)
    return b > r + 30


def is_background(pixels: np.ndarray) -> np.ndarray:
    background = np.round(np.array(render_module.BACKGROUND) * 255)
    return np.abs(pixels.astype(int) - background).max(axis=-1) <= 1


def small(name: str, n: int = 16):
    return load_scene(name).replace(grid=n)


def render_png(tmp_path, scene, backend="glsl", steps=100, solver=VERLET, **options) -> np.ndarray:
    out = tmp_path / f"{backend}.png"
    settings = RenderSettings(frames=1, every=steps, size=SIZE)
    report = render(scene, solver, backend, BackendOptions(**options), settings, str(out))
    assert report.files == [out]
    image = np.asarray(Image.open(out).convert("RGB"))
    assert image.shape == (SIZE[1], SIZE[0], 3)
    return image


def test_the_png_shows_the_cloth_where_the_cloth_is(tmp_path):
    scene, steps = small("sphere"), 100  # 0.05 s: still flat above the sphere, nothing hides it
    image = render_png(tmp_path, scene, steps=steps)
    assert is_background(image).any() and not is_background(image).all()
    # where the camera sees the particles (the edge ones may fall on the silhouette) it is cloth
    _, prev = simulate("numpy", scene, VERLET, steps, BackendOptions())  # a frame shows x(t): prev
    inner = prev.reshape(16, 16, 4)[1:-1, 1:-1, :3].reshape(-1, 3)
    col, row = np.round(frame_scene(scene, SIZE).project(inner)).astype(int).T
    assert ((col >= 0) & (col < SIZE[0]) & (row >= 0) & (row < SIZE[1])).all(), "the camera frames the sheet"
    on_cloth = is_cloth(image[row, col])
    assert on_cloth.mean() > 0.95, f"only {on_cloth.mean():.0%} of the sheet's pixels are cloth-coloured"
    assert is_collider(image).sum() > 100  # the sphere under the sheet


def test_the_floor_and_the_cylinder_are_drawn(tmp_path):
    image = render_png(tmp_path, small("cylinder"), steps=400)
    grey = (np.abs(image.astype(int) - image[..., :1]).max(axis=-1) < 12) & ~is_background(image)
    assert grey.mean() > 0.1, "the floor plane covers part of the picture"
    assert is_collider(image).sum() > 20 and is_cloth(image).sum() > 500


def test_boxes_are_drawn(tmp_path):
    scene = load_scene(str(BOX_SCENE)).replace(grid=16)
    with_boxes = is_collider(render_png(tmp_path, scene, "numpy", steps=1)).sum()
    without = is_collider(render_png(tmp_path, scene.replace(boxes=()), "numpy", steps=1)).sum()
    assert with_boxes > without + 100, f"{with_boxes} collider pixels with the boxes, {without} without"


def test_the_cube_is_closed_and_its_faces_point_out():
    vertices, indices = cube_mesh()
    tri = vertices[indices]  # (12, 3 corners, position + normal)
    face = np.cross(tri[:, 1, :3] - tri[:, 0, :3], tri[:, 2, :3] - tri[:, 0, :3])
    assert len(tri) == 12 and np.allclose(np.abs(vertices[:, :3]), 1.0)
    assert (np.einsum("ij,ij->i", face, tri[:, 0, 3:]) > 0).all(), "wound counter-clockwise seen from outside"
    assert (np.einsum("ij,ij->i", tri[:, :, :3].mean(axis=1), tri[:, 0, 3:]) > 0).all(), "normals point out"


def test_the_gif_has_the_frames_asked_for(tmp_path):
    out = tmp_path / "cloth.gif"
    seen = []
    settings = RenderSettings(frames=5, every=40, size=SIZE)
    report = render(small("sphere"), VERLET, "glsl", BackendOptions(), settings, str(out), on_frame=seen.append)
    assert seen == [1, 2, 3, 4, 5]
    with Image.open(out) as gif:
        assert gif.n_frames == 5 and report.merged == 0
        assert gif.info["loop"] == 0  # loops forever
        first = np.asarray(gif.convert("RGB"))
        gif.seek(4)
        last = np.asarray(gif.convert("RGB"))
    assert not np.array_equal(first, last), "the cloth moves between frames"


def test_a_folder_gets_one_png_per_frame(tmp_path):
    out = tmp_path / "frames"
    settings = RenderSettings(frames=3, every=10, size=SIZE)
    report = render(small("drape"), VERLET, "glsl-compute", BackendOptions(), settings, str(out) + "/")
    names = sorted(p.name for p in out.iterdir())
    assert names == ["frame_0001.png", "frame_0002.png", "frame_0003.png"]
    assert report.files == [out / name for name in names]


@pytest.mark.parametrize("backend", ["glsl", "glsl-compute"])
def test_gl_backends_draw_from_the_device_without_reading_back(tmp_path, monkeypatch, backend):
    require(backend)
    scene = small("curtain", 24)

    def no_read(self):
        raise AssertionError(f"{backend} read its state back to draw it")

    monkeypatch.setattr(glsl.GLSLBackend, "read", no_read)
    monkeypatch.setattr(glsl_compute.GLSLComputeBackend, "read", no_read)
    on_device = render_png(tmp_path, scene, backend, steps=300, strict=True)
    monkeypatch.undo()
    uploaded = render_png(tmp_path, scene, "numpy", steps=300)  # read back, numpy normals
    assert is_cloth(on_device).sum() > 300  # the curtain is in the picture
    differ = (np.abs(on_device.astype(int) - uploaded).max(axis=-1) > 0).mean()
    assert differ <= PIXEL_TOLERANCE, f"{differ:.2%} of the pixels differ from the uploaded path"


def test_a_backend_without_normals_is_drawn_with_the_harness_normals(tmp_path):
    # glsl-compute's PBD solver computes no normals: the render asks it for none and draws its
    # state read back, with grid_normals, as it draws numpy's
    require("glsl-compute")
    scene, solver = small("curtain", 24), Pbd()
    assert not capabilities("glsl-compute", "pbd").normals
    on_gl = render_png(tmp_path, scene, "glsl-compute", steps=300, solver=solver, strict=True)
    uploaded = render_png(tmp_path, scene, "numpy", steps=300, solver=solver)
    assert is_cloth(on_gl).sum() > 300
    differ = (np.abs(on_gl.astype(int) - uploaded).max(axis=-1) > 0).mean()
    assert differ <= PIXEL_TOLERANCE, f"{differ:.2%} of the pixels differ from numpy's PBD"


def test_the_numpy_path_differs_when_the_state_does(tmp_path):
    # the comparison above can fail: a different state gives a visibly different picture
    a = render_png(tmp_path, small("curtain", 24), "numpy", steps=300)
    b = render_png(tmp_path, small("curtain", 24), "numpy", steps=330)
    assert (np.abs(a.astype(int) - b).max(axis=-1) > 0).mean() > 10 * PIXEL_TOLERANCE


def test_triangles_face_the_way_the_normals_point():
    n = 5
    pos, _ = small("sphere", n).initial_state(np.float64)
    tri = pos[cloth_indices(n), :3]  # (triangles, 3 corners, xyz)
    assert len(tri) == 2 * (n - 1) ** 2
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (face[:, 1] > 0).all() and np.allclose(face[:, [0, 2]], 0)  # +y, as docs/normals.md


def test_the_camera_sees_every_corner_of_every_scene():
    for name in ("sphere", "drape", "cylinder", "curtain"):
        scene = load_scene(name)
        lo, hi = render_module.scene_bounds(scene)
        corners = np.array(np.meshgrid(*zip(lo, hi))).reshape(3, -1).T  # the box's 8 corners
        col, row = frame_scene(scene, (480, 360)).project(corners).T
        assert ((col >= 0) & (col <= 480) & (row >= 0) & (row <= 360)).all(), name
        width, height = col.max() - col.min(), row.max() - row.min()
        assert width > 0.6 * 480 or height > 0.6 * 360, f"{name} is not framed tightly"


def test_cli_renders_a_gif(tmp_path, capsys):
    out = tmp_path / "c.gif"
    args = ["render", "--scene", "sphere", "--grid", "12", "--frames", "4", "--every", "25"]
    assert cli.main([*args, "--size", "96x72", "--out", str(out)]) == 0
    with Image.open(out) as gif:
        assert gif.n_frames == 4 and gif.size == (96, 72)
    assert f"wrote {out}" in capsys.readouterr().out


@pytest.mark.parametrize(
    "args, message",
    [
        (["--frames", "0"], "--frames must be >= 1, got 0"),
        (["--every", "0"], "--every (steps between frames) must be >= 1"),
        (["--steps-per-frame", "-3"], "--every (steps between frames) must be >= 1"),
        (["--out", "cloth.jpg"], "--out must be a .png (the last frame), a .gif"),
        (["--size", "640"], "--size takes WIDTHxHEIGHT in pixels"),
        (["--size", "4x4"], "--size must be between 16x16"),
        (["--backend", "nope"], "unknown backend 'nope'"),
        (["--scene", "nope"], "unknown scene 'nope'"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, args, message):
    out = ["--out", str(tmp_path / "c.gif")] if "--out" not in args else []
    assert cli.main(["render", "--grid", "8", *out, *args]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not any(tmp_path.iterdir())
