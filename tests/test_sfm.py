"""pipeline/sfm.py helpers that need no COLMAP run (the ladder itself: tests/test_cameras_ladder.py)."""

import subprocess
import sys

import pycolmap
import pytest

from pipeline.sfm import colmap_warnings_only
from tests.conftest import ROOT


def test_colmap_info_log_stays_out_of_the_terminal_inside_and_comes_back_after(capfd):
    """Inside ``colmap_warnings_only`` COLMAP's info lines (written by its C++ logger to the process' stderr) are
    dropped and its warnings are not; on the way out the level before is restored, also after an error."""
    before = pycolmap.logging.minloglevel
    with colmap_warnings_only():
        pycolmap.logging.info("inside-info-line")
        pycolmap.logging.warning("inside-warning-line")
    pycolmap.logging.info("after-info-line")
    try:
        with colmap_warnings_only():
            raise RuntimeError("boom")
    except RuntimeError:
        pass
    out, err = capfd.readouterr()
    assert "inside-info-line" not in out + err and "inside-warning-line" in err and "after-info-line" in err
    assert pycolmap.logging.minloglevel == before


PNG_AFTER = ("import numpy as np, cv2; cv2.imwrite({path!r}, np.random.default_rng(0).integers(0, 255, (300, 400, 3),"
             " dtype=np.uint8)); print('written')")


@pytest.mark.parametrize("first", ["import pipeline; import pycolmap", "import pycolmap; import pipeline"])
def test_pipeline_loads_opencv_before_pycolmap(tmp_path, first):
    """With pycolmap loaded before OpenCV, OpenCV's PNG writer aborts the process (pycolmap's own zlib):
    ``import pipeline`` loads OpenCV first, so a PNG is written after it; a script that imported pycolmap before
    pipeline is warned in one line."""
    run = subprocess.run([sys.executable, "-c", first + "; " + PNG_AFTER.format(path=str(tmp_path / "x.png"))],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    if first.startswith("import pipeline"):
        assert run.returncode == 0 and "written" in run.stdout and "warning" not in run.stderr, run.stderr[-500:]
    else:
        assert "warning: pycolmap was imported before pipeline" in run.stderr
