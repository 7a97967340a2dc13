"""Kernel shapes chosen by measurement (clothbench/backends/tuning.py): measured once per key,
remembered on disk, measured again on --retune, never measured with tuning off."""

from __future__ import annotations

import json

import pytest

from clothbench.backends import tuning
from clothbench.errors import ClothbenchError

KEY = {"device": "test device", "driver": "1.0", "grid": "64"}


@pytest.fixture
def tuning_on(tmp_path, monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    return tmp_path


def timer(times: dict[str, float | list[float]]):
    """A time_candidate that returns `times` (a list: one value per turn) and counts its calls."""
    calls: list[str] = []

    def time_candidate(name: str) -> float:
        turn = calls.count(name)
        calls.append(name)
        if times[name] is None:
            raise ClothbenchError(f"{name} does not fit this device")
        return times[name][turn] if isinstance(times[name], list) else times[name]

    return time_candidate, calls


ROUNDS = tuning.TUNING_ROUNDS


def test_the_fastest_candidate_wins_and_is_remembered(tuning_on):
    measure, calls = timer({"a": 3.0, "b": 1.0, "c": 2.0})
    assert tuning.choose_shape("x", KEY, ["a", "b", "c"], measure) == "b"
    assert calls == ["a", "b", "c"] * ROUNDS  # the candidates take turns
    stored = json.loads((tuning_on / "tuning" / "x.json").read_text())
    (entry,) = stored.values()
    assert entry["choice"] == "b" and entry["ms"] == {"a": 3000.0, "b": 1000.0, "c": 2000.0}
    # a second backend with the same key reads the choice back without measuring
    again, calls_again = timer({"a": 0.1, "b": 1.0, "c": 2.0})
    assert tuning.choose_shape("x", KEY, ["a", "b", "c"], again) == "b" and calls_again == []


def test_retune_measures_again_and_replaces_the_choice(tuning_on):
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    measure, calls = timer({"a": 0.5, "b": 1.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure, retune=True) == "a" and len(calls) == 2 * ROUNDS
    assert tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 9.0, "b": 1.0})[0]) == "a"


def test_another_key_is_measured_on_its_own(tuning_on):
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    measure, calls = timer({"a": 1.0, "b": 2.0})
    assert tuning.choose_shape("x", {**KEY, "grid": "128"}, ["a", "b"], measure) == "a" and len(calls) == 2 * ROUNDS


def test_a_load_that_slows_one_turn_does_not_decide(tuning_on):
    # b is the faster shape, but the other core was busy during its first turn
    measure, calls = timer({"a": [2.0, 2.1, 2.0], "b": [3.5, 1.0, 1.1]})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "b"
    (entry,) = json.loads((tuning_on / "tuning" / "x.json").read_text()).values()
    assert entry["ms"] == {"a": 2000.0, "b": 1000.0}  # each candidate's fastest turn


def test_a_candidate_that_fails_is_dropped_unless_all_do(tuning_on):
    measure, calls = timer({"a": None, "b": 5.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "b"
    assert calls.count("a") == 1  # not tried again in the later turns
    with pytest.raises(ClothbenchError, match="no kernel shape runs here"):
        tuning.choose_shape("y", KEY, ["a", "b"], timer({"a": None, "b": None})[0])


def test_a_damaged_cache_file_is_measured_again_not_fatal(tuning_on):
    (tuning_on / "tuning").mkdir()
    (tuning_on / "tuning" / "x.json").write_bytes(b"\x00\xffnot json")
    assert tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0]) == "b"


def test_with_tuning_off_the_default_runs_and_nothing_is_measured(tmp_path, monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    monkeypatch.setenv("CLOTHBENCH_TUNING", "off")
    measure, calls = timer({"a": 2.0, "b": 1.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "a" and calls == []
    assert not (tmp_path / "tuning" / "x.json").exists()


def test_a_bad_tuning_setting_is_one_line(monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_TUNING", "maybe")
    with pytest.raises(ClothbenchError, match="CLOTHBENCH_TUNING must be on or off"):
        tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
