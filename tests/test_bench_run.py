"""bench/run.py: rows of a partial rerun merged into a full bench's results."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.run import merged  # noqa: E402


def _write(tmp_path, rows):
    path = tmp_path / "full.json"
    path.write_text(json.dumps({"machine": {}, "bench_seconds": 0, "results": rows}))
    return path


def test_merged_replaces_the_rerun_rows_and_keeps_the_others(tmp_path):
    gt = {"scene": "cow", "cameras": "gt", "preset": "default", "psnr": 27.0}
    photos = {"scene": "cow", "cameras": "sfm", "preset": "default", "psnr": 24.0}
    knob = {"scene": "cow", "cameras": "sfm", "preset": "default", "knob": "final adjustment", "ablation": True,
            "psnr": 25.0}
    path = _write(tmp_path, [gt, photos, knob])
    rows = merged(path, [{**photos, "psnr": 24.5}])
    assert [r["psnr"] for r in rows] == [27.0, 24.5, 25.0]


def test_merged_keeps_the_old_row_when_the_rerun_failed_and_appends_new_specs(tmp_path):
    photos = {"scene": "cow", "cameras": "sfm", "preset": "default", "psnr": 24.0}
    path = _write(tmp_path, [photos])
    new = {"scene": "jar", "cameras": "sfm", "preset": "default", "psnr": 32.0}
    rows = merged(path, [{**photos, "error": "boom"}, new])
    assert [r["psnr"] for r in rows] == [24.0, 32.0]



def test_a_bench_with_dtu_rows_makes_dtu_stages_again(tmp_path, monkeypatch):
    import bench.run as run

    monkeypatch.setattr(run, "RUNS", tmp_path)
    for name in ("dtu_all", "dtu_all-cameras_seed_1", "photos"):
        (tmp_path / name).mkdir()
    dtu = {"scene": "dtu", "cameras": "sfm", "preset": "default"}
    cow = {"scene": "cow", "cameras": "gt", "preset": "default"}
    assert run.stale_dtu_stages([cow]) == []
    assert [p.name for p in run.stale_dtu_stages([cow, dtu])] == ["dtu_all", "dtu_all-cameras_seed_1"]


def test_only_picks_any_of_its_comma_separated_words():
    from bench.run import plan, selected

    knobs = [s for s in plan(False) if selected(s, "iterations,grid")]
    assert {s["knob"] for s in knobs} == {"iterations=750", "iterations=3000", "grid=64 (no coarse-to-fine)",
                                          "grid=128"}
    assert all(selected(s, None) for s in plan(False))


def test_the_flags_keep_their_rows():
    """``--plain``: rows that train without a knob; ``--photos``: rows that run SfM (the cameras table too);
    ``--photos --trained``: the rows from photos that train."""
    from bench.run import kept, plan

    specs = plan(False)
    table = [s for s in specs if s.get("kind") == "cameras"]
    assert table and all(kept(s, photos=True) for s in table)
    assert not any(kept(s, plain=True) or kept(s, trained=True) for s in table)
    plain = [s for s in specs if kept(s, plain=True)]
    assert plain and not any(s.get("knob") for s in plain) and {s["cameras"] for s in plain} == {"gt", "sfm"}
    ours = [s for s in specs if kept(s, photos=True, trained=True)]
    assert ours and all(s["cameras"] == "sfm" for s in ours) and any(s.get("knob") for s in ours)
    assert len(ours) + len(table) == sum(kept(s, photos=True) for s in specs)
    assert all(kept(s) for s in specs)
