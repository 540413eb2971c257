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
