"""The report (pipeline/report/stage.py): the cameras stage in words, the object's size, the levels in its viewer."""

import base64
import json
import shutil
import subprocess

import pytest

from pipeline.report import stage as report
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


def test_cameras_in_doubt_are_said_with_the_pair_the_model_cannot_hold(tmp_path):
    stamp = {"rung": "default", "unexplained_pairs": [["59F0", "CEAC", 545, 41], ["A", "B", 120, 3]]}
    html = capture_section(Workspace(tmp_path / "ws"), stamp)
    assert "Cameras in doubt</b>: the model explains 41 of the 545 verified matches of 59F0 with CEAC (1 more" in html
    assert "Cameras in doubt" not in capture_section(Workspace(tmp_path / "ws"), {"rung": "default"})


def test_cameras_mapped_again_for_a_pair_in_doubt_are_said():
    stamp = {"rung": "merge-rejoined", "rejoined": True}
    assert "Cameras mapped again</b>: the first model posed a group" in capture_section(Workspace("ws"), stamp)
    assert "Cameras mapped again" not in capture_section(Workspace("ws"), {"rung": "merge"})


def test_the_objects_size_in_millimetres_with_a_board_else_the_scale_is_arbitrary():
    """The texture stage's measured box: in mm when a printed board put the mesh in metres; without one, no number."""
    metric = {"object_size": {"height": 0.1234, "width": 0.0806, "depth": 0.05, "units": "metres"}}
    assert "Size: 123 × 81 × 50 mm (height × width × depth, from the printed board)." in size_paragraph(metric)
    arbitrary = {"object_size": {"height": 1.7, "width": 0.9, "depth": 0.8, "units": "arbitrary"}}
    text = size_paragraph(arbitrary)
    assert "the scale is arbitrary" in text and "mm" not in text and "1.7" not in text
    assert size_paragraph({}) == ""


def test_the_viewer_switches_between_the_inlined_levels(tmp_path, monkeypatch):
    """A button per level whose GLB is inlined (lightest first, within the budget); the page's script, run by node
    on a stand-in for the viewer element, swaps the viewer's source to the level asked for and back to the default;
    a level past the budget is left to its file."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (make setup-web needs it too)")
    for name, size in (("preview", 300), ("full", 900)):
        folder = tmp_path / "levels" / name
        folder.mkdir(parents=True)
        (folder / "textured.glb").write_bytes(name.encode() * size)
    monkeypatch.setattr(report, "INLINED_LEVELS_BYTES", 3000)
    stamp = {"faces": 100, "glb_bytes": 2000, "levels": {"preview": {"faces": 50, "glb_bytes": 2100},
                                                        "full": {"faces": 400, "glb_bytes": 3600}}}
    page = report.levels_paragraph(stamp, tmp_path, viewer=True)
    assert page.count("<button") == 2 and "open the file" in page and 'showLevel(&quot;preview&quot;)' in page
    script = page[page.index("<script>") + len("<script>"):page.index("</script>")]
    run = ("const shown = {textContent: ''}; const viewer = {src: 'data:default'};"
           "const document = {getElementById: id => id === 'viewer' ? viewer : shown};" + script +
           "showLevel('preview'); const a = [viewer.src, shown.textContent];"
           "showLevel('default'); console.log(JSON.stringify([a, [viewer.src, shown.textContent]]));")
    out = subprocess.run([node, "-e", run], capture_output=True, text=True, check=True).stdout
    (preview_src, preview_name), back = json.loads(out)
    assert base64.b64decode(preview_src.split(",", 1)[1]) == b"preview" * 300 and preview_name == "preview"
    assert back == ["data:default", "default"]
    assert report.levels_paragraph(stamp, tmp_path, viewer=False).count("<button") == 0
