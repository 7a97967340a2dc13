"""`clothbench view`: the window, its keys, backend switching and the profiler.

The logic runs on moderngl-window's headless window (EGL, in this process); a real window
runs under Xvfb (xvfb-run, in a subprocess), driven by --keys. Every check reads what the
viewer leaves behind: the --log lines, the --save state, the --screenshot.

Bit-exactness of a switched strict run: every registry backend is bit-exact in strict mode
with NumPy float32, and switching moves the state as float32 arrays read from one backend
and uploaded unchanged to the next, so the switched run ends with the bits of an unswitched
NumPy run of the same step count. The one caveat is llvmpipe's fragment shader (`glsl`),
which flushes subnormal floats (docs/semantics.md, "Subnormal floats"): the sphere scene at
its own grid, 64, never reaches float32's subnormal range within 4000 steps (glsl strict
compared with NumPy every 10 steps from the start: bit-exact throughout), and these runs
stay inside that (at most 600 steps, glsl for 150 of them).
"""

from __future__ import annotations

import json
import signal
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from clothbench import cli
from clothbench.errors import ClothbenchError
from clothbench.harness.simulate import simulate
from clothbench.backends import backend_class
from clothbench.backends.gl import context as gl_context
from clothbench.viewer import keys as view_keys
from clothbench.viewer import overlay_text
from clothbench.viewer.camera import Trackball
from clothbench.viewer.draw import DIM, GAP, PAD, WARN, Glyphs, clear_span, fit_lines, layout
from clothbench.viewer.profiler import FrameProfile, Stage, gl_timer_queries
from clothbench.model.scene import load_setup

from conftest import assert_bit_exact, lines_in, require, wait_until

pytestmark = pytest.mark.serial  # holds a GL context (a window): one xdist worker

pytest.importorskip("moderngl_window", reason="moderngl-window not installed (pip install moderngl-window)")

SPF = 10  # steps per frame in every run here
SIZE = "320x240"
RUN = "import sys; from clothbench.cli import main; sys.exit(main(sys.argv[1:]))"  # `clothbench` in a subprocess


def headless(tmp_path, monkeypatch, *args, frames=12) -> tuple[list[dict], dict]:
    """Run the viewer on the headless window; (its log lines, its saved state)."""
    require("glsl")  # the headless window is an EGL context
    log, save = tmp_path / "events.jsonl", tmp_path / "state.npz"
    argv = ["view", "--headless", "--frames", str(frames), "--steps-per-frame", str(SPF), "--size", SIZE,
            "--log", str(log), "--save", str(save), *args]  # fmt: skip
    assert cli.main(argv) == 0
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert [line["frame"] for line in lines] == list(range(1, frames + 1))
    with np.load(save) as state:
        return lines, {k: state[k] for k in state.files}


def unswitched(steps: int, scene: str = "sphere"):
    s = load_setup(scene)
    return simulate("numpy", s.scene, s.solver, steps)


def child(tree: dict, *names: str) -> dict:
    """The stage at names[0]/names[1]/... below `tree` (a log line's profiler)."""
    for name in names:
        tree = next(c for c in tree["children"] if c["name"] == name)
    return tree


def assert_same_state(saved: dict, expected, what: str) -> None:
    for name, want in zip(("pos", "prev"), expected):
        assert_bit_exact(saved[name].view(np.uint32), want.view(np.uint32), f"{what}: {name}")


# --- keys ------------------------------------------------------------------------------


def test_a_key_script_is_frame_key_pairs_in_keyboard_names():
    assert view_keys.parse_script("40:F3, 80:f2,120:P,120:space") == {40: ["F3"], 80: ["F2"], 120: ["P", "space"]}
    for bad in ("F3", "0:F1", "x:F1", "10:F13", "10:enter"):
        with pytest.raises(ClothbenchError, match="--keys|unknown key"):
            view_keys.parse_script(bad)


def test_the_f_keys_follow_the_chapter_then_the_registry():
    from clothbench.backends import BACKENDS

    keys = view_keys.backend_keys()
    assert [keys[f"F{i}"] for i in range(1, 6)] == ["numpy", "glsl", "opencl", "cuda", "glsl-compute"]
    assert sorted(keys.values()) == sorted(BACKENDS)
    # past F12, which is as far as moderngl-window's keys go, shift and an F-key: a script presses them too
    assert view_keys.parse_script("7:shift+f2") == {7: ["shift+F2"]} and "shift+F2" in keys
    assert list(view_keys.GRID_KEYS.values()) == [32, 64, 128, 256, 512]


def test_bad_input_is_one_line_before_any_window(monkeypatch, capsys):
    for argv, says in (
        (["view", "--keys", "300:F1", "--frames", "200"], "after the last"),
        (["view", "--headless"], "--headless needs --frames"),
        (["view", "--screenshot", "out.jpg", "--frames", "1"], "takes a .png"),
        (["view", "--backend", "nope"], "unknown backend"),
    ):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and says in err, err


def test_without_a_display_it_says_what_to_do_in_one_line():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    done = subprocess.run(
        [sys.executable, "-c", RUN, "view", "--frames", "5"], env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2
    err = done.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "xvfb-run" in err and "--screenshot" in err and "--record" in err


# --- the profiler and the camera -------------------------------------------------------------


def test_a_stage_tree_gives_shares_of_its_parent_and_of_the_frame():
    p = FrameProfile()
    with p.stage("step"):
        with p.stage("kernel"):
            pass
    p.add("step/kernel/predict", 3.0)
    root = p.finish()
    root.ms, root.children[0].ms, root.find("step/kernel").ms = 20.0, 8.0, 6.0
    tree = root.as_dict(root.ms)
    step = tree["children"][0]
    assert (step["of_parent"], step["of_frame"]) == (0.4, 0.4)
    kernel = step["children"][0]
    assert (kernel["of_parent"], kernel["of_frame"]) == (0.75, 0.3)
    assert kernel["children"][0] == {"name": "predict", "ms": 3.0, "of_parent": 0.5, "of_frame": 0.15}
    assert Stage("x").as_dict(0.0)["of_frame"] == 0.0  # no division by zero


def test_timer_queries_of_a_software_rasteriser_are_not_called_a_gpus():
    class Device:
        renderer = "llvmpipe (LLVM 15.0.6, 256 bits)"

    real, note = gl_timer_queries(Device())
    assert not real and "not a GPU's clock" in note
    Device.renderer = "NVIDIA H200/PCIe/SSE2"
    assert gl_timer_queries(Device())[0]


def test_a_lent_context_is_what_the_gl_backends_get_until_it_is_given_back():
    require("glsl")
    own = gl_context.get_device()
    window, inner = object(), object()  # lend_device takes any device: nothing draws here
    with gl_context.lend_device(window):
        assert gl_context.get_device() is window
        with gl_context.lend_device(inner):
            assert gl_context.get_device() is inner
        assert gl_context.get_device() is window
    assert gl_context.get_device() is own


def test_the_trackball_turns_the_view_and_keeps_it_a_rotation():
    s = load_setup("sphere")
    ball = Trackball(s.scene, (640, 480))
    home, up = ball.camera().eye.copy(), ball.orientation[1].copy()
    ball.drag(400, 240, 80, 0)  # a drag to the right through the middle turns about the view's up
    r = ball.orientation
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-9)
    eye = ball.camera().eye
    assert not np.allclose(eye, home) and np.allclose(r[1], up, atol=1e-9)
    before = np.linalg.norm(eye - ball.centre)
    assert np.isclose(before, np.linalg.norm(home - ball.centre))
    ball.zoom(0.5)
    assert np.isclose(np.linalg.norm(ball.camera().eye - ball.centre), before / 2)
    ball.home()
    assert np.allclose(ball.camera().eye, home)
    ball.turn(0, 2)  # the arrow keys: a turntable about the vertical, the eye's height kept
    assert np.isclose(ball.camera().eye[1], home[1]) and not np.allclose(ball.camera().eye, home)
    assert np.isclose(ball.orientation[0][1], 0.0, atol=1e-12)  # the view's right axis stays level


def test_the_cloth_is_framed_clear_of_the_panels():
    """The drape's cloth starts level at the top of its bounds: `render`'s framing would put its
    left corner under the run panel. Framed between the top panels, every
    particle is on screen and none under a panel, in a wide window and a narrower one (moved,
    and made smaller where the width needs it); a span under half the window keeps the
    whole-window framing."""
    scene = load_setup("drape").scene
    cloth = scene.initial_state()[0][:, :3]
    glyphs = Glyphs()
    run = ("top-left", ["x" * 50])
    placed = layout([run, ("bottom-left", ["keys"])], (1280, 720), glyphs)
    left, right = clear_span(placed, 1280)
    assert (left, right) == (GAP + 50 * glyphs.width + 2 * PAD + GAP, 1280)  # the run panel's edge only
    for size in ((1280, 720), (1024, 768)):
        ball = Trackball(scene, size)
        before = ball.camera().project(cloth)[:, 0]
        ball.keep_clear_of(left, size[0])
        after = ball.camera().project(cloth)[:, 0]
        assert before.min() < left, size  # the case: without it, a corner is under the panel
        assert left <= after.min() and after.max() <= size[0], size
        ball.keep_clear_of(left - 40, size[0])  # the panel a frame narrower: the frame stays
        assert np.array_equal(ball.camera().project(cloth)[:, 0], after), size
    ball.resize((1280, 720))
    assert ball.clear == (0, 1280)  # a new window size: the panels are placed again
    # the profiler opened at the right: the span between the panels, or the whole window
    profiler = ("top-right", ["y" * 30])
    left, right = clear_span(layout([run, profiler], (1600, 900), glyphs), 1600)
    assert right == 1600 - GAP - (30 * glyphs.width + 2 * PAD) - GAP
    ball = Trackball(scene, (1600, 900))
    ball.keep_clear_of(left, right)
    x = ball.camera().project(cloth)[:, 0]
    assert left <= x.min() and x.max() <= right
    narrow = Trackball(scene, (800, 600))
    whole = narrow.camera().view_projection
    narrow.keep_clear_of(*clear_span(layout([run], (800, 600), glyphs), 800))  # over half of it
    assert np.array_equal(narrow.camera().view_projection, whole)


# --- the viewer on the headless window ---------------------------------------------------------


def test_switching_backends_keeps_the_cloth_where_it_is_bit_for_bit(tmp_path, monkeypatch):
    for name in ("opencl", "glsl", "glsl-compute"):
        require(name)
    lines, saved = headless(
        tmp_path, monkeypatch, "--backend", "numpy", "--strict", "--keys", "4:F3,8:F2,12:F5", frames=16
    )
    assert [lines[i]["backend"] for i in (2, 3, 7, 11, 15)] == [
        "numpy",
        "opencl",
        "glsl",
        "glsl-compute",
        "glsl-compute",
    ]
    assert "switched numpy -> opencl at step 30" in lines[3]["events"][0]
    assert [line["drawn_from"] for line in (lines[2], lines[3], lines[7], lines[11])] == [
        "readback",
        "readback",
        "device",
        "device",
    ]
    assert lines[-1]["step"] == 16 * SPF
    assert_same_state(saved, unswitched(16 * SPF), "numpy -> opencl -> glsl -> glsl-compute")


def test_an_unusable_backend_says_why_and_nothing_else_changes(tmp_path, monkeypatch):
    lines, saved = headless(
        tmp_path, monkeypatch, "--backend", "numpy", "--keys", "3:F4,4:F2", "--solver", "pbd", frames=6
    )
    from clothbench.backends import availability

    cuda = lines[2]["events"][0]
    assert ("unavailable" in cuda) != availability("cuda").usable, cuda  # here: no CUDA device
    assert "glsl has no pbd solver" in lines[3]["events"][0]
    assert {line["backend"] for line in lines} == {"numpy"}
    assert lines[-1]["step"] == 6 * SPF  # the run went on through both
    s = load_setup("sphere").replace(solver="pbd")
    assert_same_state(saved, simulate("numpy", s.scene, s.solver, 6 * SPF), "numpy pbd, unswitched")


def test_grid_reset_pause_and_single_step_count_steps_exactly(tmp_path, monkeypatch):
    keys = "3:space,5:N,7:space,9:R,10:1"
    lines, saved = headless(tmp_path, monkeypatch, "--backend", "numpy", "--keys", keys, frames=12)
    steps = [line["step"] for line in lines]
    assert steps == [10, 20, 20, 20, 30, 30, 40, 50, 10, 10, 20, 30]
    assert [line["steps"] for line in lines][2:5] == [0, 0, SPF]
    assert lines[8]["events"] == ["reset: the cloth starts again"]
    assert [line["grid"] for line in lines][8:10] == [64, 32]
    assert saved["pos"].shape == (32 * 32, 4)
    s = load_setup("sphere").replace(grid=32)
    assert_same_state(saved, simulate("numpy", s.scene, s.solver, 30), "32x32 after the grid key")


def test_the_shadow_run_stops_where_float64_cannot_keep_up(tmp_path, monkeypatch):
    lines, _ = headless(tmp_path, monkeypatch, "--backend", "numpy", "--keys", "2:E,3:4,4:E", frames=4)
    assert "shadow_error" in lines[1] and "shadow_error" not in lines[2]
    assert lines[2]["events"][-1] == "shadow off: float64 NumPy keeps up only to 128x128"
    assert "keeps up only to 128x128, this is 256x256" in lines[3]["events"][0] and "shadow_error" not in lines[3]


def test_collider_keys_rebuild_the_scene_and_keep_the_cloth(tmp_path, monkeypatch):
    lines, saved = headless(tmp_path, monkeypatch, "--backend", "numpy", "--keys", "3:S,5:G,7:S", frames=8)
    assert [line["colliders"]["spheres"] for line in lines] == [1, 1, 0, 0, 0, 0, 1, 1]
    assert [line["colliders"]["planes"] for line in lines][4] == 1  # the floor of the cylinder scene
    assert lines[2]["events"] == ["spheres off at step 20"] and lines[2]["step"] == 30  # the run goes on
    # the state went on from where it was: the first two frames are the scene's own steps
    assert lines[6]["step"] == 70 and np.isfinite(saved["pos"]).all()


def test_the_profiler_tree_and_the_shadow_error_are_in_every_line(tmp_path, monkeypatch):
    require("glsl-compute")
    lines, _ = headless(tmp_path, monkeypatch, "--backend", "glsl-compute", "--keys", "2:P,2:E,5:1,6:F1", frames=8)
    for line in lines:
        tree = line["profiler"]
        assert tree["name"] == "frame" and tree["of_frame"] == 1.0
        assert {"step", "draw", "present"} <= {c["name"] for c in tree["children"]}
        assert sum(c["of_parent"] for c in tree["children"]) <= 1.001  # the parts are inside the frame
        step = child(tree, "step")
        assert [c["name"] for c in step["children"]] == ["upload", "kernel", "readback", "normals"]
        assert sum(c["of_parent"] for c in step["children"]) <= 1.001
        assert line["ms"] == step["ms"] and line["fps"] > 0
    assert "shadow_error" not in lines[0]
    error = lines[3]["shadow_error"]
    assert error["since_step"] == 10 and 0 < error["rms_m"] <= error["max_m"] < 1e-3  # float32 against float64
    assert lines[4]["shadow_error"]["since_step"] == 0  # the grid key restarted it with the cloth
    assert [c["name"] for c in child(lines[3]["profiler"], "shadow")["children"]] == ["readback", "f64 step", "compare"]
    assert lines[3]["drawn_from"] == "device" and lines[6]["drawn_from"] == "readback"
    assert child(lines[3]["profiler"], "step", "readback")["ms"] == 0  # drawn from the device
    assert child(lines[6]["profiler"], "step", "readback")["ms"] > 0
    assert child(lines[5]["profiler"], "build")["ms"] > 0  # F1 built numpy: outside the step


def test_the_profiler_opens_a_backend_s_own_stages(tmp_path, monkeypatch):
    require("opencl")
    lines, _ = headless(tmp_path, monkeypatch, "--backend", "opencl", "--solver", "pbd", "--keys", "2:P", frames=3)
    assert "children" not in child(lines[0]["profiler"], "step", "kernel")
    stages = [c["name"] for c in child(lines[2]["profiler"], "step", "kernel")["children"]]
    assert "predict" in stages and len(stages) >= 3, stages


# --- a real window under Xvfb ------------------------------------------------------------------


def test_a_real_window_under_xvfb_driven_by_keys(tmp_path):
    if shutil.which("xvfb-run") is None:
        pytest.skip("Xvfb not installed (apt-get install xvfb xauth)")
    for name in ("opencl", "glsl", "glsl-compute"):
        require(name)
    shot, log, save = tmp_path / "s.png", tmp_path / "l.jsonl", tmp_path / "v.npz"
    frames = 60
    argv = ["view", "--scene", "sphere", "--backend", "numpy", "--strict", "--keys", "15:F3,30:F2,45:F5,50:P",
            "--frames", str(frames), "--steps-per-frame", str(SPF), "--size", "480x360",
            "--screenshot", str(shot), "--log", str(log), "--save", str(save)]  # fmt: skip
    done = subprocess.run(
        ["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", sys.executable, "-c", RUN, *argv],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert len(lines) == frames and all(line["ms"] > 0 for line in lines)
    assert [lines[i]["backend"] for i in (13, 14, 29, 44)] == ["numpy", "opencl", "glsl", "glsl-compute"]
    switches = [e for line in lines for e in line["events"] if e.startswith("switched")]
    expected = ["numpy -> opencl at step 140", "opencl -> glsl at step 290", "glsl -> glsl-compute at step 440"]
    assert [e.split(" (")[0] for e in switches] == [f"switched {x}" for x in expected]
    with np.load(save) as saved:
        assert_same_state({k: saved[k] for k in saved.files}, unswitched(frames * SPF), "switched under Xvfb")
    image = np.asarray(Image.open(shot).convert("RGB"))
    assert image.shape == (360, 480, 3)
    h, w = image.shape[:2]
    middle = image[int(0.45 * h) : int(0.8 * h), int(0.3 * w) : int(0.7 * w)].astype(int)
    r, b = middle[..., 0], middle[..., 2]
    cloth = (r > 1.5 * b) & (r - b > 30)  # the checker's red and gold, lit or in shade
    assert cloth.mean() > 0.2, f"only {cloth.mean():.1%} of the middle is the cloth's colour"


def _x_server(tmp_path) -> tuple[subprocess.Popen, str]:
    """Xvfb on a display it picks, leading a process group of its own as a terminal's foreground
    group would; (the server, its DISPLAY) once it takes connections."""
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb not installed (apt-get install xvfb)")
    ready_r, ready_w = os.pipe()
    server = subprocess.Popen(
        ["Xvfb", "-displayfd", str(ready_w), "-screen", "0", "1024x768x24", "-nolisten", "tcp"],
        pass_fds=[ready_w],
        process_group=0,
        stderr=open(tmp_path / "xvfb.err", "w"),
    )
    os.close(ready_w)
    with os.fdopen(ready_r) as ready:
        number = ready.readline().strip()  # written once the server listens; nothing if it failed
    if not number:
        server.wait()
        raise AssertionError(f"Xvfb did not start: {(tmp_path / 'xvfb.err').read_text()[-1000:]}")
    return server, f":{number}"


@pytest.mark.parametrize(
    "sig, to_group",
    [(signal.SIGINT, False), (signal.SIGINT, True), (signal.SIGTERM, False)],
    ids=["ctrl-c-to-the-viewer", "ctrl-c-to-the-viewer-and-its-x-server", "sigterm-to-the-viewer"],
)
def test_a_signal_stops_a_window_with_one_line_and_exit_130(tmp_path, sig, to_group):
    """A terminal's Ctrl-C under xvfb-run reaches the X server too, and it exits first: the
    viewer then finds its display gone, and Xlib's own handler would print XIO lines and exit 1."""
    require("glsl")  # an OpenGL 3.3 implementation to draw the window with
    server, display = _x_server(tmp_path)
    log = tmp_path / "l.jsonl"
    try:
        argv = ["view", "--scene", "drape", "--backend", "numpy", "--steps-per-frame", "1", "--size", "320x240",
                "--log", str(log)]  # fmt: skip
        viewer = subprocess.Popen(
            [sys.executable, "-c", RUN, *argv],
            env=dict(os.environ, DISPLAY=display),
            process_group=server.pid,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        wait_until(lambda: lines_in(log) >= 2, viewer, "the window's frames")
        if to_group:
            os.killpg(server.pid, sig)
        else:
            viewer.send_signal(sig)
        out, err = viewer.communicate(timeout=120)
        assert "XIO" not in err and "Traceback" not in err, err[-2000:]
        assert viewer.returncode == 130 and err.splitlines() == ["clothbench: interrupted"], err[-2000:]
        assert out == ""
        if to_group:  # the case is the one it names: the server went with the same signal
            assert server.wait(timeout=120) is not None
    finally:
        if server.poll() is None:
            server.terminate()
            server.wait(timeout=120)


def test_a_refusal_wider_than_the_window_is_wrapped_inside_it():
    with pytest.raises(ClothbenchError) as refused:
        backend_class("newton", "verlet")  # newton has PBD only: its refusal names every Verlet backend
    refusal = f"F10 newton: cannot run: {refused.value}"
    hint = overlay_text.HINT.format(view_keys.backend_key_span())
    glyphs = Glyphs()
    for w, h in ((1280, 720), (320, 240)):
        chars = (w - 2 * GAP - 2 * PAD) // glyphs.width
        assert len(refusal) > chars  # the case: wider than the window
        lines = fit_lines([(refusal, WARN), (hint, DIM)], chars)
        assert all(len(text) <= chars for text, _ in lines), (w, h)
        said = [text for text, colour in lines if colour == WARN]
        assert " ".join(said).split() == refusal.split(), (w, h)  # every word, in order, in its colour
        [(_, x, y, image)] = layout([("bottom-left", [(refusal, WARN), (hint, DIM)])], (w, h), glyphs)
        ph, pw = image.shape[:2]
        assert GAP <= x and x + pw <= w - GAP and GAP <= y and y + ph <= h - GAP, (w, h)
        assert ph == len(lines) * glyphs.height + 2 * PAD, (w, h)  # a row for every line: none cut off
