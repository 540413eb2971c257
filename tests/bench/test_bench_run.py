"""bench/run.py: rows of a partial rerun merged into a full bench's results."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

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
    failed = {"scene": "mouse", "cameras": "sfm", "preset": "default", "error": "boom"}
    rows = merged(path, [{**photos, "error": "boom"}, new, failed])
    assert [r.get("psnr") for r in rows] == [24.0, 32.0, None]  # a new spec's failure is shown, not dropped


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


def test_stale_picks_the_training_rows_of_older_defaults(tmp_path):
    """``--stale``: the specs whose row in the JSON ran with defaults older than DEFAULTS_VERSION (a row without a
    version is version 1); the cameras table, which does not train, never."""
    from bench.report import DEFAULTS_VERSION
    from bench.run import plan, spec_key, stale_specs

    specs = plan(False)
    knob = next(s for s in specs if s.get("knob") == "grid=128")
    plain = next(s for s in specs if s["scene"] == "jar" and not s.get("knob") and s.get("kind") != "cameras")
    table = next(s for s in specs if s.get("kind") == "cameras")
    current = next(s for s in specs if s["scene"] == "book" and s.get("kind") != "cameras")
    path = _write(tmp_path, [{**knob, "defaults": DEFAULTS_VERSION - 1}, {**plain}, {**table},
                             {**current, "defaults": DEFAULTS_VERSION}])
    picked = [spec_key(s) for s in stale_specs(specs, path)]
    assert len(picked) == 2 and set(picked) == {spec_key(plain), spec_key(knob)}
    assert stale_specs([current, table], path) == []


def test_only_picks_a_presets_rows():
    from bench.run import plan, selected

    rows = [s for s in plan(False) if selected(s, "preview")]
    assert {(s["scene"], s["cameras"]) for s in rows} == {("cow", "gt"), ("cow", "sfm"), ("dtu", "sfm")}
    assert all(s["preset"] == "preview" for s in rows)


def test_a_preset_that_sets_the_photo_stages_gets_its_own_dtu_stages():
    from bench.evaluate import photo_stage_preset

    assert photo_stage_preset("preview") == "preview"  # its masks options
    assert photo_stage_preset("fast") == "fast"  # its cameras' object verification
    assert photo_stage_preset("balanced") is None  # training and mesh options only: DTU's shared stages
    assert photo_stage_preset(None) is None
