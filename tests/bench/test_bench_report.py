"""bench/report.py: rows trained with older defaults are marked in the table and in the findings."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.report import DEFAULTS_VERSION, STALE_NOTE, ablation_findings, table  # noqa: E402


def _row(knob=None, defaults=None, psnr=25.0):
    r = {"scene": "cow", "cameras": "sfm", "preset": "default", "psnr": psnr, "chamfer_rel": 0.003, "fscore": 0.99,
         "seconds": {"cameras": 10.0, "train": 50.0}, "total_s": 60.0, "peak_rss_gb": 1.2,
         "pose": {"center_err_rel_max": 0.004, "rot_err_deg_mean": 0.05}, "psnr_gt_pose": psnr}
    if knob:
        r.update(knob=knob, ablation=True)
    if defaults is not None:
        r["defaults"] = defaults
    return r


def test_table_marks_only_the_rows_of_older_defaults():
    old, new = _row(), _row("final adjustment", DEFAULTS_VERSION)
    lines = table([old, new], {}).splitlines()
    old_line = next(x for x in lines if x.startswith("| cow | photos only | default"))
    new_line = next(x for x in lines if x.startswith("| cow | photos only | final adjustment"))
    assert "†" in old_line and "†" not in new_line
    assert lines[-1] == STALE_NOTE


def test_table_has_no_note_when_every_row_is_current():
    md = table([_row(defaults=DEFAULTS_VERSION)], {})
    assert "†" not in md and STALE_NOTE not in md


def test_a_finding_with_one_side_of_older_defaults_is_marked():
    base, knob = _row(defaults=DEFAULTS_VERSION), _row("final adjustment", psnr=26.0)
    marked = ablation_findings([knob], [base, knob])
    assert len(marked) == 1 and "from photos †, without / with it:" in marked[0]
    fresh = ablation_findings([{**knob, "defaults": DEFAULTS_VERSION}], [base, {**knob, "defaults": DEFAULTS_VERSION}])
    assert len(fresh) == 1 and "†" not in fresh[0]


def test_real_captures_table_gives_each_stages_seconds_and_where_it_ran():
    from bench.report import real_table

    secs = {"cameras": 150.0, "masks": 40.0, "depth": 1.0, "train": 90.0, "mesh": 9.0, "texture": 14.0}
    rows = [{"scene": "blowtorch", "cameras": "sfm", "preset": "default", "registered": "66/67", "seconds": secs,
             "mask_iou": 0.951, "psnr": 20.5, "psnr_gain_fit": 22.25, "machine": {"model": "Xeon", "cores": 2}},
            {"scene": "mouse", "cameras": "sfm", "preset": "default", "knob": "x", "registered": "1/59"},
            {"scene": "cow", "cameras": "sfm", "preset": "default", "registered": "20/20"}]
    text = real_table(rows).splitlines()
    assert len(text) == 5 and "66/67 | 150 | 40 | 1 | 90 | 9 | 14 | 304 | 0.951 | 20.50 (22.25) |" in text[2]
    assert text[-1] == "Measured on Xeon, 2 cores (rows without a machine: the bench's)."
    assert real_table(rows[1:]) == ""  # a knob's row and a synthetic scene are no real-capture rows
    failed = {"scene": "blowtorch", "cameras": "sfm", "preset": "default",
              "error": "pipeline.errors.StageError: only 19/67 photos registered (missing: …)"}
    assert "| 19/67: stopped, too few posed |" in real_table([failed]).splitlines()[2]


def test_a_change_of_some_presets_leaves_the_others_rows_current(monkeypatch):
    import bench.report as report

    monkeypatch.setattr(report, "DEFAULTS_CHANGES", {2: ("every preset", None), 3: ("a schedule", ("default", "fast"))})

    def row(preset, version):
        return {**_row(defaults=version), "preset": preset}

    assert report.is_stale(row("default", 2)) and report.is_stale(row("fast", 2))
    assert not report.is_stale(row("balanced", 2))  # version 3 leaves balanced as it was
    assert report.is_stale(row("balanced", 1))  # version 2 changed every preset
    assert not any(report.is_stale(row(p, 3)) for p in ("default", "fast", "balanced"))
    assert report.stale(row("balanced", 2)) == "" and report.stale(row("balanced", 2), row("fast", 2)) == " †"
