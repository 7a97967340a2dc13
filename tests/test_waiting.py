"""What a command says while it waits (clothbench/progress.py `waiting`): on a terminal, a line
naming the wait (probing backends, building and warming up a backend, tuning, drawing a
report's figures); with stderr piped, nothing at all. The terminal is a fake one (a stream
that says it is a tty); the delay before a wait is drawn is set to 0 (drawn at once) or to
forever (never drawn), so nothing here depends on how long anything takes."""

from __future__ import annotations

import io
import json
import sys
import time
from contextlib import contextmanager
from typing import Iterator

import pytest

from clothbench.backends import tuning
from clothbench.cli import main
from clothbench import progress
from clothbench.progress import LazyProgress, waiting
from test_tuning import KEY, machine, tuning_on  # noqa: F401  (fixtures: a recorded machine, tuning on)


class FakeTerminal(io.StringIO):
    """stderr as a terminal: rich draws on it what it would draw on a real one."""

    def isatty(self) -> bool:
        return True


@contextmanager
def on_a_terminal() -> Iterator[FakeTerminal]:
    """stderr a terminal for the body of the `with`: set in the test itself, since pytest's
    capture sets sys.stderr again after the fixtures, as the test starts."""
    term, saved = FakeTerminal(), sys.stderr
    sys.stderr = term
    try:
        yield term
    finally:
        sys.stderr = saved


@pytest.fixture
def drawn_at_once(monkeypatch):
    """Every wait and bar drawn from its start, on a terminal rich draws live on."""
    monkeypatch.setenv("TERM", "xterm-256color")  # rich draws nothing live on a dumb one
    monkeypatch.setattr(progress, "SHOW_AFTER_S", 0.0)


def test_backends_on_a_terminal_says_it_is_probing_them_and_prints_the_same_listing(drawn_at_once, capsys):
    with on_a_terminal() as term:
        assert main(["backends", "--json"]) == 0
    on_terminal = capsys.readouterr()
    assert "probing backends: numpy" in term.getvalue()
    assert "probing backends: OpenCL devices" in term.getvalue()
    assert main(["backends", "--json"]) == 0  # stderr piped (captured)
    piped = capsys.readouterr()
    assert piped.err == ""
    assert json.loads(piped.out) == json.loads(on_terminal.out)  # the probes are cached: the same rows


def test_run_on_a_terminal_names_the_build_then_the_warm_up(drawn_at_once, capsys):
    with on_a_terminal() as term:
        assert main(["run", "--grid", "4", "--steps", "3", "--json"]) == 0
    said = term.getvalue()
    assert said.index("building numpy") < said.index("warming up numpy: first steps (a JIT compiles here)")
    assert json.loads(capsys.readouterr().out)["steps"] == 3  # stdout is still one JSON object


def test_report_on_a_terminal_says_it_is_drawing_the_figures_while_it_draws_them(
    drawn_at_once, tmp_path, capsys, monkeypatch
):
    import clothbench.reports.html as html

    said_while_drawing = []

    def build_report(files, title):  # the figures themselves are test_report.py's
        said_while_drawing.append(term.getvalue())
        return "<html></html>", 0

    monkeypatch.setattr(html, "build_report", build_report)
    out = tmp_path / "r.html"
    with on_a_terminal() as term:
        assert main(["report", "tests/data/accuracy-drape-epyc-2026-11-22.csv", "--out", str(out)]) == 0
    assert "building the report: drawing its figures" in said_while_drawing[0]
    assert capsys.readouterr().out == f"wrote {out} (0 figures from 1 files: accuracy)\n"


@pytest.mark.parametrize(
    "argv",
    [["run", "--grid", "4", "--steps", "3", "--json"], ["backends", "--json"]],
    ids=["run", "backends"],
)
def test_piped_stderr_gets_nothing_even_when_every_wait_is_due_at_once(argv, drawn_at_once, capsys):
    assert main(argv) == 0
    assert capsys.readouterr().err == ""  # what these commands write on stderr without the waits


def test_a_wait_ended_before_its_delay_draws_nothing(drawn_at_once, monkeypatch):
    monkeypatch.setattr(progress, "SHOW_AFTER_S", float("inf"))
    with on_a_terminal() as term, waiting("probing backends"):
        pass
    assert term.getvalue() == ""


def test_a_worker_process_draws_nothing_on_the_terminal_it_shares(drawn_at_once, monkeypatch):
    monkeypatch.setattr(progress.multiprocessing, "parent_process", lambda: object())  # as in a sweep's row
    with on_a_terminal() as term, waiting("tuning c"):
        pass
    assert term.getvalue() == ""


def test_a_wait_inside_another_says_itself_then_gives_the_line_back(drawn_at_once):
    with on_a_terminal() as term, waiting("building c"):
        with waiting("tuning c"):
            pass
    said = term.getvalue()
    assert said.index("building c") < said.index("tuning c") < said.rindex("building c")
    assert not progress._waits.pending()  # the line is cleared: the next wait starts its own


def test_a_wait_while_the_sweeps_bar_is_drawn_is_said_in_the_bar(drawn_at_once):
    with on_a_terminal() as term:
        with LazyProgress(10, "sweep c n=16") as bar:
            bar.update(1)
            with waiting("tuning c"):
                assert not progress._waits.pending()  # no second display beside the bar
            assert progress._bar is bar
        assert progress._bar is None
    assert "sweep c n=16: tuning c" in term.getvalue()


def test_tuning_names_each_candidate_and_draws_nothing_while_one_is_timed(drawn_at_once, tuning_on, monkeypatch):  # noqa: F811
    monkeypatch.setattr(progress, "REDRAW_S", 0.001)  # a redrawing thread not held back would draw many times
    drawn_while_timed = []

    with on_a_terminal() as term:

        def time_candidate(name: str) -> float:
            before = len(term.getvalue())
            time.sleep(0.02)  # the redrawing thread's chances to draw: it must take none
            drawn_while_timed.append(len(term.getvalue()) - before)
            return {"a": 2e-3, "b": 1e-3}[name]

        assert tuning.choose_shape("test", KEY, ["a", "b"], time_candidate) == "b"
    said = term.getvalue()
    assert "tuning test (measured once, then cached): a, turn 1 of 3" in said
    assert f"b, turn {tuning.TUNING_ROUNDS} of {tuning.TUNING_ROUNDS}" in said
    assert drawn_while_timed == [0] * (2 * tuning.TUNING_ROUNDS)


def test_a_drawn_bar_draws_only_at_its_updates_never_during_a_timed_chunk(drawn_at_once):
    with on_a_terminal() as term, LazyProgress(10, "numpy n=16") as bar:
        bar.update(1)
        drawn = len(term.getvalue())
        time.sleep(0.3)  # a chunk between two updates: rich's own refresh thread would draw three times
        assert len(term.getvalue()) == drawn
        bar.update(2)
        assert len(term.getvalue()) > drawn
