"""bench/profile_stages.py: the functions that take a stage's time, and its one-line refusals."""

import cProfile
import pstats
import sys

import pytest

from bench import profile_stages as profile


def _busy(n: int) -> float:
    total = 0.0
    for i in range(n):  # the work in this function's own body: no generator or built-in to share its time with
        total += i * 0.5
    return total


def _idle() -> None:
    return None


def test_the_busiest_function_comes_first_with_its_calls():
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(3):
        _busy(200_000)
        _idle()
    prof.disable()
    rows = profile.top_functions(pstats.Stats(prof), 5)
    assert len(rows) <= 5 and [r["own_s"] for r in rows] == sorted((r["own_s"] for r in rows), reverse=True)
    assert rows[0]["function"].endswith("(_busy)") and rows[0]["calls"] == 3, rows
    assert rows[0]["function"].startswith("tests/bench/test_bench_profile_stages.py:")  # short, from the project's root


def test_the_summary_has_a_row_per_stage():
    rows = [{"stage": "masks", "seconds": 12.34, "functions": [{"function": "a.py:1(f)", "own_s": 5.0}]},
            {"stage": "train", "seconds": 60.0, "functions": []}]
    text = profile.table(rows, 3)
    assert text.splitlines()[2] == "| masks | 12.3 | a.py:1(f) 5.0 s |" and "| train | 60.0 |  |" in text


def test_an_unknown_stage_or_scene_is_one_line(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["profile_stages.py", "--scene", "cow_floor", "--stages", "masks,paint"])
    with pytest.raises(SystemExit, match="unknown stage.*paint"):
        profile.main()
    with pytest.raises(SystemExit, match="no such scene"):
        profile.scene_photos("no_such_scene")
