"""pipeline/sfm.py helpers that need no COLMAP run (the ladder itself: tests/test_cameras_ladder.py)."""

import pycolmap

from pipeline.sfm import colmap_warnings_only


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
