"""Every fact about a backend is its registry entry's (backends/__init__.py): the name tables
and figures give it, its figures' panel, whether it is GPU-style, its viewer key, whether a
forked child may run it; and every backend class names the device clock it reads. A backend
added to the registry, and nowhere else, is in `backends`, the sweep, every figure and table
of `report` that lists backends, and the viewer's keys."""

from __future__ import annotations

import csv
import dataclasses
import json
import re
from pathlib import Path

import pytest

from clothbench.backends import (
    BACKENDS,
    PEERS,
    PLATFORMS,
    Availability,
    Backend,
    BackendEntry,
    BackendOptions,
    availability,
    backend_class,
)
from clothbench.cli import main
from clothbench.harness.sweep import run_sweep
from clothbench.harness.sweep_settings import SweepSettings
from clothbench.harness.timing import DEVICE_TIMERS
from clothbench.reports.figures_common import platform_color, platform_title
from clothbench.viewer import keys as view_keys
from clothbench.model.scene import load_setup

ROOT = Path(__file__).resolve().parents[1]
FACTS = ("display", "platform", "gpu_style", "view_key", "fork_safe")
TWIN = "numpy-twin"
TWIN_DISPLAY = "NumPy twin"
TWIN_KEY = "shift+F3"  # the first key no registry backend has
ACCURACY_COSTS = ("ms_per_step", "ms_per_sim_s")  # an accuracy or stability row's costs
SWEEP_COSTS = ("ms_median", "ms_min", "ms_max", "ms_iqr", "ms_per_sim_s")  # a sweep row's


# --- (a) every entry declares every fact, each a value the readers take -----------------------


def test_an_entry_cannot_leave_a_fact_out():
    numpy = BACKENDS["numpy"]
    given = {f: getattr(numpy, f) for f in FACTS}
    for fact in FACTS:
        with pytest.raises(TypeError, match=fact):
            BackendEntry("x", numpy.verlet, **{f: v for f, v in given.items() if f != fact})


def test_every_entry_declares_every_fact_with_a_value_its_readers_take():
    displays = [e.display for e in BACKENDS.values()]
    assert all(displays) and len(set(displays)) == len(displays), displays  # a legend tells them apart
    for name, e in BACKENDS.items():
        assert e.platform in PLATFORMS, (name, e.platform)
        assert (e.platform == PEERS) == e.peer, name  # a peer's panel is the peers' panel, and only a peer's
        assert platform_color(platform_title(e.platform)), name
        assert isinstance(e.gpu_style, bool) and isinstance(e.fork_safe, bool), name
        assert not (e.gpu_style and e.peer), name  # GPU-style is clothbench's own side of the peer table
        assert e.view_key in view_keys.BACKEND_KEY_NAMES, (name, e.view_key)
    # one backend a key, every backend a key (backend_keys refuses a shared one)
    assert sorted(view_keys.backend_keys().values()) == sorted(BACKENDS)


def test_only_numpys_own_steppers_are_fork_safe():
    # a forked child inherits whatever driver state the parent holds: only host NumPy holds none
    for name, e in BACKENDS.items():
        modules = {backend_class(name, s).__module__ for s in e.solvers()}
        assert e.fork_safe == all(m.startswith("clothbench.backends.numpy.") for m in modules), name


def test_every_backend_class_names_the_device_clock_it_reads():
    assert not hasattr(type("Undeclared", (Backend,), {}), "device_timer")  # no default to inherit
    for name, e in BACKENDS.items():
        for solver in e.solvers():
            cls = backend_class(name, solver)
            assert hasattr(cls, "device_timer"), f"{cls.__name__} ({name} {solver}) declares no device_timer"
            timer = cls.__dict__.get("device_timer", cls.device_timer)
            # a property where the driver decides (GL); else '' or a documented clock
            assert isinstance(timer, property) or timer == "" or timer in DEVICE_TIMERS, (name, timer)


def test_readme_says_the_view_keys_the_registry_gives():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    paragraph = text[text.index("`view` is the chapter's demo") :].split("\n\n")[0]
    said = dict(re.findall(r"\*\*((?:shift\+)?F\d+)\*\* ([a-z0-9-]+)", paragraph))
    assert said == view_keys.backend_keys()


def test_an_unknown_key_is_refused_naming_the_keys_the_help_lists(capsys):
    with pytest.raises(Exception, match=re.escape(view_keys.KEYS_TEXT)):
        view_keys.parse_script("10:F13")  # moderngl-window has no F13: shift+F1 is the key past F12
    with pytest.raises(SystemExit):
        main(["view", "--help"])
    out = capsys.readouterr().out
    assert view_keys.KEYS_TEXT in out
    assert all(f"{key} {name}" in out for key, name in view_keys.backend_keys().items())


# --- (b) a backend added to the registry, and nowhere else -------------------------------------


@pytest.fixture
def twin(monkeypatch):
    """numpy under another name, in the registry alone: its own display name and view key."""
    entry = dataclasses.replace(BACKENDS["numpy"], name=TWIN, display=TWIN_DISPLAY, view_key=TWIN_KEY)
    monkeypatch.setitem(BACKENDS, TWIN, entry)
    # the sweep's rows run in forked children, which inherit this process's registry
    monkeypatch.delenv("CLOTHBENCH_START_METHOD", raising=False)
    availability.cache_clear()
    yield entry
    availability.cache_clear()


def test_the_twin_is_listed_by_backends(twin, monkeypatch, capsys):
    import clothbench.backends as registry

    probe = registry.availability
    # every other backend's probe imports its library (torch, jax, ...: seconds each): not this test's
    unprobed = Availability(False, "not probed in this test")
    monkeypatch.setattr(registry, "availability", lambda n: probe(n) if n in ("numpy", TWIN) else unprobed)
    assert main(["backends", "--json"]) == 0
    rows = {r["backend"]: r for r in json.loads(capsys.readouterr().out)}
    assert list(rows) == list(BACKENDS) and rows[TWIN]["usable"] and rows[TWIN]["kind"] == "clothbench"


def test_the_twin_is_in_the_viewers_keys(twin, capsys):
    from clothbench.viewer.profiler import FrameProfile
    from clothbench.viewer.session import Session

    assert view_keys.backend_keys()[TWIN_KEY] == TWIN and view_keys.key_of(TWIN) == TWIN_KEY
    assert f"{TWIN_KEY} {TWIN}" in " ".join(what for _, what in view_keys.help_lines())
    assert view_keys.parse_script(f"3:{TWIN_KEY.upper()}") == {3: [TWIN_KEY]}
    with pytest.raises(SystemExit):
        main(["view", "--help"])
    assert f"{TWIN_KEY} {TWIN}" in capsys.readouterr().out
    setup = load_setup("sphere").replace(grid=8)
    session = Session(setup.scene, setup.solver, "numpy", BackendOptions())
    assert session.press(TWIN_KEY, FrameProfile()) and session.backend_name == TWIN, session.message


def _cheaper(row: dict, costs: tuple[str, ...], than: dict | None = None) -> dict:
    """`row` with each of its `costs` columns that has a value at 0.9 of `than`'s (its own by
    default)."""
    than = row if than is None else than
    return dict(row, **{c: str(0.9 * float(than[c])) for c in costs if than.get(c)})


def _with_twin(src: Path, dst: Path, labels: tuple[str, ...]) -> Path:
    """numpy's rows of `labels` from a committed results CSV and the same rows as the twin's,
    a little cheaper, so that a Pareto front keeps the twin's (tied errors: the cheaper wins)."""
    with open(src, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["backend"] == "numpy" and r["label"] in labels]
    copies = [_cheaper(dict(r, backend=TWIN, label=r["label"].replace("numpy", TWIN)), ACCURACY_COSTS) for r in rows]
    with open(dst, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows + copies)
    return dst


def test_the_twin_is_in_the_sweep_and_every_figure_and_backend_table_of_the_report(twin, tmp_path):
    sweep = tmp_path / "sweep.csv"
    settings = SweepSettings(setup=load_setup("sphere"), grids=[8, 12], steps=2, repeats=2, bounds=False)
    run_sweep(["numpy", TWIN], settings, sweep)
    with open(sweep, newline="") as f:
        rows = list(csv.DictReader(f))
    ok = {(r["backend"], r["precision"], r["grid"]) for r in rows if r["status"] == "ok"}
    assert {(TWIN, p, g) for p in ("f32", "f64") for g in ("8", "12")} <= ok, rows
    # the sweep's speed-against-error figure names only the rows on its Pareto front, and of
    # two identical backends the clock picks which is cheaper: each twin row's costs set to 0.9
    # of numpy's same row, as _with_twin does for the accuracy rows, so that the front is the
    # twin's on every run (0.9 of the twin's own timing was not enough: at these grids two
    # timings of the same code differ by more than a tenth on a busy machine, and CI's once did)
    numpy_row = {(r["precision"], r["grid"]): r for r in rows if r["backend"] == "numpy"}
    with open(sweep, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(
            _cheaper(r, SWEEP_COSTS, than=numpy_row[r["precision"], r["grid"]]) if r["backend"] == TWIN else r
            for r in rows
        )
    results = ROOT / "results"
    accuracy = _with_twin(
        results / "accuracy-drape.csv", tmp_path / "accuracy.csv", ("numpy f32", "numpy f32/pbd-jacobi/10it")
    )
    stability = _with_twin(
        results / "stability.csv", tmp_path / "stability.csv", ("numpy f32", "numpy f32/pbd-coloured/10it")
    )
    out = tmp_path / "report.html"
    assert main(["report", str(sweep), str(accuracy), str(stability), "--out", str(out)]) == 0
    page = out.read_text(encoding="utf-8")

    figures = re.findall(r'<svg[^>]*aria-label="([^"]*)"(.*?)</svg>', page, re.S)
    assert len(figures) >= 6, [label for label, _ in figures]
    sweep_part = page[: page.index("<h2>Accuracy")]
    for label, svg in figures:
        assert TWIN in svg or TWIN_DISPLAY in svg, f"{label!r} does not draw the twin"
        if svg in sweep_part:  # the sweep's legends give the registry's display name
            assert TWIN_DISPLAY in svg, label
    # a table whose rows are backends names the twin, the sweep's Pareto front's too (the
    # twin's rows are the cheaper)
    listing = [t for t in re.findall(r"<table.*?</table>", page, re.S) if re.search(r"<th>backend", t)]
    assert len(listing) >= 5, len(listing)
    for table in listing:
        assert TWIN in table, re.findall(r"<th>(.*?)</th>", table)[:4]
