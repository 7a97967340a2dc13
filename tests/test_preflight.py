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
    "energy": ["energy", "--backends", "numpy", "--grid", "4", "--steps", "200", "--damped-steps", "200"],
}  # fmt: skip
OUT = {"run": "--save", "sweep": "--out", "accuracy": "--out", "stability": "--out", "energy": "--out"}


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


@pytest.mark.parametrize("command", ["run", "sweep", "accuracy", "energy"])
def test_a_binary_scene_file_is_one_line(command, tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_bytes(b"\xff\xfe\x00\x81binary")
    assert main([*COMMANDS[command], "--scene", str(scene)]) == 2
    _one_line_error(capsys, "not UTF-8")


@pytest.mark.parametrize("command", ["run", "sweep", "accuracy", "stability", "energy"])
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


# Every command's bad input, one line and exit 2 before any work: {bin} a binary file, {dir} a
# folder, {missing} no file, {blocked} a path under a file (it cannot be written), {sweep} a
# good sweep CSV. The commands run/sweep/accuracy/stability have the tests above as well.
REFUSALS = [
    ("plot {bin}", "not UTF-8"),
    ("plot {dir}", "is a directory"),
    ("plot {missing}", "no such file"),
    ("plot {sweep} --out {blocked}", "cannot"),
    ("report {bin}", "not UTF-8"),
    ("report {dir}", "is a directory"),
    ("report {missing}", "no such file"),
    ("report {sweep} --out {blocked}.html", "cannot write"),
    ("compare {bin} {sweep}", "not UTF-8"),
    ("compare {sweep} {bin}", "not UTF-8"),
    ("compare {sweep} {dir}", "is a directory"),
    ("compare {sweep} {missing}", "no such file"),
    ("render --backend numpy --frames 1 --out {blocked}.png", "cannot write"),
    ("render --backend numpy --frames 1 --out {blocked}/", "cannot write"),
    ("render --backend numpy --frames 1 --out {dir}/x.txt", "--out must be"),
    ("render --backend numpy --frames 1 --out {dir}/r.png --dt 1e-30", "too small for float32"),
    ("render --backend numpy --frames 1 --out {dir}/r.png --dt 1e39", "too large for float32"),
    ("render --backend numpy --frames 1 --out {dir}/r.png --grid 100000", "needs about"),
    ("render --backend numpy --frames 1 --out {dir}/r.png --scene {bin}", "not UTF-8"),
    ("render --backend numpy --frames 1 --out {dir}/r.png --scene {dir}", "is a directory"),
    ("render --backend numpy --frames 1 --out {dir}/r.png --scene {missing}", "unknown scene"),
    ("view --headless --backend numpy --frames 1 --screenshot /proc/clothbench-x.png", "cannot write"),
    ("view --headless --backend numpy --frames 1 --record {blocked}.gif", "no folder"),
    ("view --headless --backend numpy --frames 1 --save {dir}", "takes a .npz"),
    ("view --headless --backend numpy --frames 1 --dt 1e-30", "too small for float32"),
    ("view --headless --backend numpy --frames 1 --dt 1e39", "too large for float32"),
    ("view --headless --backend numpy --frames 1 --grid 100000", "needs about"),
    ("view --headless --backend numpy --frames 1 --scene {bin}", "not UTF-8"),
    ("view --headless --backend numpy --frames 1 --scene {dir}", "is a directory"),
    ("advise --max-error 1e-3 --csv {bin}", "not UTF-8"),
    ("advise --max-error 1e-3 --csv {dir}", "directory"),
    ("advise --max-error 1e-3 --csv {missing}", "No such file"),
    ("advise --max-error 1e-3 --scene {bin}", "not UTF-8"),
    ("advise --max-error 1e-3 --run --backends numpy --out {blocked}.csv", "cannot write"),
    ("accuracy --backends numpy --grid 4 --levels 2 --time 0.01 --scene {bin}", "not UTF-8"),
    ("stability --backends numpy --grid 8 --steps 100 --scenes flat --out {blocked}.csv", "cannot write"),
    ("sweep --backends numpy --grids 4 --steps 3 --repeat 1 --scene {dir}", "is a directory"),
    ("run --backend numpy --grid 4 --steps 3 --scene {missing}", "unknown scene"),
]


@pytest.mark.parametrize("line, words", REFUSALS, ids=[r[0].split()[0] + ": " + r[0] for r in REFUSALS])
def test_every_command_refuses_bad_input_in_one_line(line, words, tmp_path, capsys, monkeypatch):
    from pathlib import Path

    from matplotlib.figure import Figure

    def drawn(*a, **k):  # plot drew every figure (seconds) before it found --out unwritable
        raise AssertionError("a figure was drawn before the input was checked")

    monkeypatch.setattr(Figure, "draw", drawn)

    binary = tmp_path / "binary.csv"
    binary.write_bytes(bytes(range(256)) * 4)
    folder = tmp_path / "folder"
    folder.mkdir()
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    sweep = Path(__file__).parents[1] / "results" / "cpu-llvmpipe-pocl.csv"
    names = dict(bin=binary, dir=folder, missing=tmp_path / "missing.csv", blocked=blocker / "out", sweep=sweep)
    argv = [part.format(**names) for part in line.split()]
    assert main(argv) == 2
    _one_line_error(capsys, words)
    assert not [p for p in folder.iterdir()], "a refused command wrote something"


def test_advise_refuses_an_accuracy_run_written_as_measured_but_not_finished(tmp_path, capsys):
    import csv

    from clothbench.analysis.convergence import AccuracyRow
    from clothbench.cli.study_files import early_cells

    row = early_cells(AccuracyRow("drape", 32, "rest", 0.002, 0.1, "numpy", "numpy f32", "f32", "cpu", 0.001, 100))
    path = tmp_path / "acc.csv"
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        w.writeheader()
        w.writerow(row)
    assert main(["advise", "--max-error", "1e-3", "--csv", str(path)]) == 2
    _one_line_error(capsys, "unfinished", "--resume")


# --- output paths, and positions float32 cannot carry ----------------------------------


@pytest.mark.parametrize("name", ["result", "x.npy"])
def test_run_save_refuses_a_name_np_savez_would_change(name, tmp_path, capsys, no_work):
    # np.savez would write result.npz and x.npy.npz: a path the user did not name
    assert main([*COMMANDS["run"], "--save", str(tmp_path / name)]) == 2
    _one_line_error(capsys, "--save takes a .npz file")
    assert not list(tmp_path.iterdir())


def test_run_save_refuses_a_folder(tmp_path, capsys, no_work):
    folder = tmp_path / "outdir"
    folder.mkdir()
    assert main([*COMMANDS["run"], "--save", str(folder)]) == 2
    _one_line_error(capsys, "is a directory")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["outdir"]  # no outdir.npz beside it


def test_run_says_where_it_saved(tmp_path, capsys):
    path = tmp_path / "state.npz"
    assert main([*COMMANDS["run"], "--save", str(path)]) == 0
    assert capsys.readouterr().out.rstrip().endswith(f"wrote {path}")
    assert main([*COMMANDS["run"], "--save", str(path), "--json"]) == 0
    out, err = capsys.readouterr()
    assert f"wrote {path}" in err and f"wrote {path}" not in out  # stdout stays one JSON object


@pytest.mark.parametrize(
    "argv",
    [[*COMMANDS["run"], "--save", "{tmp}/no/such/x.npz"],
     ["render", "--backend", "numpy", "--frames", "1", "--out", "{tmp}/nodir/sub/c.png"],
     ["render", "--backend", "numpy", "--frames", "1", "--out", "{tmp}/nodir/sub/"]],
)  # fmt: skip
def test_a_missing_parent_folder_is_refused_and_none_is_made(argv, tmp_path, capsys, no_work):
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    _one_line_error(capsys, "cannot write", "there is no folder", "make it first")
    assert not list(tmp_path.iterdir()), "a refused command made a folder"


def test_render_into_a_new_frames_folder_of_an_existing_one_is_checked_and_not_left(tmp_path):
    preflight.check_writable(tmp_path / "frames" / "frame_0001.png", "--out", new_folder=True)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("new_folder", [False, True], ids=["file", "frames-folder"])
def test_a_signal_during_the_writable_probe_leaves_no_probe_behind(tmp_path, monkeypatch, new_folder):
    # the SIGTERM run's save test caught an empty --save file left behind: the signal came between
    # the probe's create and its unlink. Here it comes at exactly that point, sent by the probe's
    # own close, so the handler (KeyboardInterrupt, as cli/args.sigterm_interrupts installs) must
    # wait for the probe to be removed
    import os
    import signal

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    closed = []
    real_close = os.close

    def close_then_signal(fd):
        real_close(fd)
        closed.append(fd)
        os.kill(os.getpid(), signal.SIGTERM)

    path = tmp_path / "frames" / "x.png" if new_folder else tmp_path / "x.npz"
    previous = signal.signal(signal.SIGTERM, interrupt)
    monkeypatch.setattr(preflight.os, "close", close_then_signal)
    try:
        with pytest.raises(KeyboardInterrupt):
            preflight.check_writable(path, new_folder=new_folder)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert closed, "the probe never ran"
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "line, words",
    [("height = 1e4", ["height 10000 is too far from 0 for float32", "np.spacing", "never moves"]),
     ("size = 1e30", ["size 1e+30 overflows float32", "squared length"])],
)  # fmt: skip
def test_positions_float32_cannot_carry_are_refused_before_work(line, words, tmp_path, capsys, no_work):
    scene = tmp_path / "s.toml"
    scene.write_text(f"[cloth]\n{line}\n")
    for command in ("run", "sweep"):
        assert main([*COMMANDS[command], "--scene", str(scene)]) == 2
        _one_line_error(capsys, *words)


def test_a_far_cloth_runs_in_f64_and_a_near_one_in_f32(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text("[cloth]\nheight = 1e4\n")
    assert main([*COMMANDS["run"], "--scene", str(scene), "--precision", "f64", "--json"]) == 0
    scene.write_text("[cloth]\nheight = 20\n")  # g dt^2 is above half the spacing at 20 m: it moves
    assert main([*COMMANDS["run"], "--scene", str(scene), "--json"]) == 0


def test_a_default_results_path_makes_its_folders(tmp_path, monkeypatch):
    # accuracy/stability/pbd-study write results/... by default: that folder is theirs to make
    monkeypatch.chdir(tmp_path)
    with pytest.raises(Exception, match="there is no folder results"):
        preflight.check_writable("results/x.csv")
    preflight.check_writable("results/study/x.csv", make_folders=True)
    assert (tmp_path / "results" / "study").is_dir()


# --- a truncated CSV is said to be truncated ------------------------------------------


def _cut(tmp_path, where: str):
    from pathlib import Path

    text = (Path(__file__).parents[1] / "results" / "cpu-llvmpipe-pocl.csv").read_text()
    lines = text.splitlines(keepends=True)
    if where == "header":
        cut = lines[0][:20]
    elif where == "first row":
        cut = lines[0] + lines[1][: len(lines[1]) // 2]
    else:  # the last row
        cut = text[: len(text) - len(lines[-1]) // 2]
    path = tmp_path / f"cut-{where.replace(' ', '-')}.csv"
    path.write_text(cut)
    return path, len(lines) - 1


@pytest.mark.parametrize("where", ["header", "first row"])
@pytest.mark.parametrize("command", ["plot", "compare"])
def test_a_csv_cut_before_any_whole_row_is_refused_as_truncated(command, where, tmp_path, capsys):
    path, _ = _cut(tmp_path, where)
    argv = (
        ["plot", str(path), "--out", str(tmp_path / "figs")] if command == "plot" else ["compare", str(path), str(path)]
    )
    assert main(argv) == 2
    _one_line_error(capsys, str(path), f"truncated inside its {where}")


def test_compare_warns_that_a_truncated_last_row_was_dropped(tmp_path, capsys):
    from clothbench.harness.sweep_csv import read_sweep

    path, rows = _cut(tmp_path, "last row")
    assert len(read_sweep(path)) == rows - 1
    capsys.readouterr()
    whole = tmp_path / "whole.csv"
    whole.write_text((tmp_path / "cut-last-row.csv").read_text().rsplit("\n", 1)[0] + "\n")
    assert main(["compare", str(whole), str(path)]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"warning: {path} is truncated: its last line" in err and "dropped" in err, err
