"""pipeline/colmaplib.py and the package's import order: pycolmap after OpenCV, COLMAP's logger without log files
and without info lines on the terminal (each case in a fresh interpreter: both are per process)."""

import os
import subprocess
import sys

import pytest

from tests.conftest import ROOT

PNG_AFTER = ("import numpy as np, cv2; cv2.imwrite({path!r}, np.random.default_rng(0).integers(0, 255, (300, 400, 3),"
             " dtype=np.uint8)); print('written')")


def _python(code: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                          env={**os.environ, **env})


@pytest.mark.parametrize("first", ["import pipeline; import pycolmap", "import pycolmap; import pipeline"])
def test_pipeline_loads_opencv_before_pycolmap(tmp_path, first):
    """With pycolmap loaded before OpenCV, OpenCV's PNG writer aborts the process (pycolmap's own zlib):
    ``import pipeline`` loads OpenCV first, so a PNG is written after it; a script that imported pycolmap before
    pipeline is warned in one line."""
    run = _python(first + "; " + PNG_AFTER.format(path=str(tmp_path / "x.png")))
    if first.startswith("import pipeline"):
        assert run.returncode == 0 and "written" in run.stdout and "warning" not in run.stderr, run.stderr[-500:]
    else:
        assert "warning: pycolmap was imported before pipeline" in run.stderr


def test_colmap_writes_no_log_files_and_keeps_info_lines_off_the_terminal(tmp_path):
    """COLMAP's logger leaves no file in the temporary folder (glog's default: one per level and process there);
    its info lines stay off stderr, also after a bundle adjustment (which turns them back on) once
    ``warnings_only`` ran again; its warnings and errors reach stderr; a rung's child puts the info lines back."""
    temp = tmp_path / "temp"
    temp.mkdir()
    code = ("from pipeline.colmaplib import pycolmap, warnings_only, info_to_stderr\n"
            "pycolmap.logging.info('info-at-start'); pycolmap.logging.warning('warning-line')\n"
            "pycolmap.bundle_adjustment(pycolmap.Reconstruction(), pycolmap.BundleAdjustmentOptions())\n"
            "warnings_only(); pycolmap.logging.info('info-after-adjustment')\n"
            "info_to_stderr(); pycolmap.logging.info('info-in-a-child')\n")
    run = _python(code, TMPDIR=str(temp), GLOG_log_dir="")
    assert run.returncode == 0, run.stderr[-500:]
    assert "info-at-start" not in run.stderr and "info-after-adjustment" not in run.stderr
    assert "warning-line" in run.stderr and "Need at least one registered frame" in run.stderr  # COLMAP's error
    assert "info-in-a-child" in run.stderr
    assert list(temp.iterdir()) == []
