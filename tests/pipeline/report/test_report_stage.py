"""The report's words for the cameras stage (pipeline/report/stage.py)."""

from pipeline.report.stage import capture_section, size_paragraph
from pipeline.workspace import Workspace


def test_the_ladder_in_words_with_rungs_not_tried_and_a_global_model(tmp_path):
    """A stamp whose budget ran out after the first rung and its global mapper: every rung is said, those not tried
    with why, and the report is written (a rung without seconds once stopped it with a KeyError)."""
    stamp = {"rung": "default-global", "rungs": [
        {"rung": "default", "seconds": 377.5, "registered": 19, "dropped": []},
        {"rung": "default-global", "seconds": 33.9, "registered": 55, "dropped": ["a.png", "b.png"]},
        {"rung": "guided", "skipped": "time budget spent"},
        {"rung": "global", "seconds": 20.0, "registered": 40, "rejected": 12},
    ]}
    html = capture_section(Workspace(tmp_path / "ws"), stamp)
    assert "default: 19 registered in 377.5 s" in html
    assert "default-global: 55 registered in 33.9 s, 2 views with wrong poses dropped" in html
    assert "guided: not tried (time budget spent)" in html and "global: 40 registered in 20.0 s, rejected" in html
    assert "kept <b>default-global</b>" in html


def test_the_objects_size_in_millimetres_with_a_board_else_the_scale_is_arbitrary():
    """The texture stage's measured box: in mm when a printed board put the mesh in metres; without one, no number."""
    metric = {"object_size": {"height": 0.1234, "width": 0.0806, "depth": 0.05, "units": "metres"}}
    assert "Size: 123 × 81 × 50 mm (height × width × depth, from the printed board)." in size_paragraph(metric)
    arbitrary = {"object_size": {"height": 1.7, "width": 0.9, "depth": 0.8, "units": "arbitrary"}}
    text = size_paragraph(arbitrary)
    assert "the scale is arbitrary" in text and "mm" not in text and "1.7" not in text
    assert size_paragraph({}) == ""
