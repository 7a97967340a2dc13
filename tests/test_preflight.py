"""Every bad input refused in one line before any work: an output path that cannot be
written (found before the run, not after it), a scene file that is not text, a grid the
machine cannot hold, and values float32 turns into nothing or into inf."""

from __future__ import annotations

import pytest

from clothbench.cli import main
from clothbench.harness import preflight

COMMANDS = {
    "run": ["run", "--backend", "numpy", "--grid", "4", "--steps", "3"],
    "sweep": ["sweep", "--backends", "numpy", "--grids", "4", "--steps", "3", "--repeat", "1"],
    "accuracy": ["accuracy", "--backends", "numpy", "--grid", "4", "--levels", "2", "--time", "0.01"],
    "stability": ["stability", "--backends", "numpy", "--grid", "8", "--steps", "100", "--scenes", "flat",
                  "--stiffness", "1000"],
}  # fmt: skip
OUT = {"run": "--save", "sweep": "--out", "accuracy": "--out", "stability": "--out"}


def _one_line_error(capsys, *words) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert err.startswith("clothbench: error: "), err
    for w in words:
        assert w in err, err
    return err


@pytest.fixture
def no_work(monkeypatch):
    """Any backend built means work began: the check came too late."""
    import importlib

    import clothbench.backends as backends

    def refuse(*a, **k):
        raise AssertionError("work began before the input was checked")

    # imported before the patch, so that none binds the patched function as its own
    users = [importlib.import_module(m) for m in ("clothbench.harness.sweep", "clothbench.analysis.convergence")]
    monkeypatch.setattr(backends, "create_backend", refuse)
    for m in users:
        monkeypatch.setattr(m, "create_backend", refuse)


@pytest.mark.parametrize("command", COMMANDS)
def test_an_output_path_that_cannot_be_written_is_refused_before_the_run(command, tmp_path, capsys, no_work):
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    bad = str(blocker / "out.csv")  # a folder that is a file
    assert main([*COMMANDS[command], OUT[command], bad]) == 2
    _one_line_error(capsys, "cannot write")


@pytest.mark.parametrize("command", COMMANDS)
def test_an_output_path_that_is_a_directory_is_refused(command, tmp_path, capsys, no_work):
    path = tmp_path / ("d.npz" if command == "run" else "d.csv")
    path.mkdir()
    assert main([*COMMANDS[command], OUT[command], str(path)]) == 2
    _one_line_error(capsys, "directory")


@pytest.mark.parametrize("command", ["run", "sweep", "accuracy"])
def test_a_binary_scene_file_is_one_line(command, tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_bytes(b"\xff\xfe\x00\x81binary")
    assert main([*COMMANDS[command], "--scene", str(scene)]) == 2
    _one_line_error(capsys, "not UTF-8")


@pytest.mark.parametrize("command", ["run", "sweep", "accuracy", "stability"])
def test_a_grid_the_machine_cannot_hold_is_refused_before_work(command, capsys, monkeypatch, no_work):
    monkeypatch.setattr(preflight, "available_memory", lambda: 64 * 2**20)  # 64 MiB
    args = list(COMMANDS[command])
    flag = "--grids" if command == "sweep" else "--grid"
    args[args.index(flag) + 1] = "1024"
    assert main(args) == 2
    _one_line_error(capsys, "grid 1024 needs about", "available")


def test_memory_estimate_grows_with_grid_precision_and_jobs():
    assert preflight.row_bytes(64, "f64") > preflight.row_bytes(64, "f32") > preflight.row_bytes(32, "f32")
    preflight.check_memory([64], available=2**30)  # fits
    with pytest.raises(Exception, match="fewer --jobs"):
        preflight.check_memory([512], jobs=64, available=2**30)


@pytest.mark.parametrize("command", ["run", "sweep"])
@pytest.mark.parametrize(
    "dt, words",
    [("1e-200", ["dt^2", "too small for float32"]), ("1e-20", ["dt^2", "too small for float32"]),
     ("1e30", ["dt^2 overflows"])],
)  # fmt: skip
def test_a_dt_float32_breaks_is_one_line(command, dt, words, capsys):
    assert main([*COMMANDS[command], "--dt", dt]) == 2
    _one_line_error(capsys, *words)


def test_accuracy_dts_float32_breaks_are_one_line(capsys):
    assert main([*COMMANDS["accuracy"], "--dts", "1e-20,2e-20"]) == 2
    _one_line_error(capsys, "too small for float32")


@pytest.mark.parametrize(
    "line, words",
    [("stiffness = 1e-45", ["stiffness", "too small for float32"]),
     ("mass = 1e-39", ["mass", "too small for float32"]),
     ("stiffness = 1e38\nmass = 1e-30", ["stiffness * dt^2 / mass", "overflows float32"])],
)  # fmt: skip
def test_scene_constants_float32_breaks_are_one_line(line, words, tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(f"[cloth]\n{line}\n")
    assert main([*COMMANDS["run"], "--scene", str(scene)]) == 2
    _one_line_error(capsys, *words)


def test_accuracy_stiffness_float32_breaks_is_one_line(capsys):
    assert main([*COMMANDS["accuracy"], "--stiffness", "1e-45"]) == 2
    _one_line_error(capsys, "too small for float32")


@pytest.mark.parametrize("k, words", [("1e-45", ["too small for float32"]), ("1e39", ["too large for float32"])])
def test_stability_stiffness_float32_breaks_is_one_line_before_work(k, words, capsys, no_work):
    args = list(COMMANDS["stability"])
    args[args.index("--stiffness") + 1] = f"1000,{k}"
    assert main(args) == 2
    _one_line_error(capsys, *words)
