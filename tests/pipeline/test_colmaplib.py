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


def test_a_quiet_bundle_adjustment_prints_nothing_and_stderr_comes_back():
    """pycolmap's bundle adjustment logs its header at info level whatever the logger's settings: inside ``quiet``
    none of its lines reach stderr, and stderr works again after the block, also when the block raised."""
    code = ("import os\nfrom pipeline.colmaplib import pycolmap, quiet\n"
            "ba = lambda: pycolmap.bundle_adjustment(pycolmap.Reconstruction(), pycolmap.BundleAdjustmentOptions())\n"
            "with quiet():\n    ba()\nos.write(2, b'after-quiet\\n')\n"
            "try:\n    with quiet():\n        raise KeyError('inside')\n"
            "except KeyError:\n    os.write(2, b'after-raise\\n')\n"
            "ba()\n")
    run = _python(code)
    assert run.returncode == 0, run.stderr[-500:]
    before, _, after = run.stderr.partition("after-quiet")
    assert "bundle_adjustment" not in before and "after-raise" in after
    assert "Global bundle adjustment" in after  # outside the block: what the block kept off


def test_a_model_cut_short_by_a_full_disk_is_said(tmp_path, monkeypatch):
    """COLMAP's model writer leaves its files cut short when the disk fills, and says nothing (reading them back is
    no check: a count read from the cut has its reader allocate gigabytes): a model written where no space is left
    is a full disk, and the model already there stays as it was."""
    import shutil
    from collections import namedtuple

    import numpy as np

    from dvr import atomic
    from pipeline.colmaplib import pycolmap, write_model

    rec = pycolmap.Reconstruction()
    for _ in range(20):
        rec.add_point3D(np.random.default_rng(0).random(3), pycolmap.Track(), np.zeros(3, np.uint8))
    write_model(rec, tmp_path / "best")
    assert pycolmap.Reconstruction(tmp_path / "best").num_points3D() == 20
    before = {p.name: p.read_bytes() for p in (tmp_path / "best").iterdir()}
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(atomic.shutil, "disk_usage", lambda path: usage(1 << 30, 1 << 30, 4096))
    with pytest.raises(atomic.DiskFull, match="best"):
        write_model(pycolmap.Reconstruction(), tmp_path / "best")
    monkeypatch.setattr(atomic.shutil, "disk_usage", shutil.disk_usage)
    assert {p.name: p.read_bytes() for p in (tmp_path / "best").iterdir()} == before
    assert sorted(q.name for q in tmp_path.iterdir()) == ["best"]


def test_colmaps_full_disk_is_the_stages_not_the_next_rungs(tmp_path):
    """A rung's child that failed because the disk filled (SQLite's words in its log) is the stage's full disk: the
    ladder does not climb on to the next rung, which needs the disk too."""
    import errno

    from pipeline.colmaplib import raise_if_disk_full

    log = tmp_path / "default.log"
    log.write_text("I20 feature_extraction.cc:42] Processed file [3/20]\nSQLite error: database or disk is full\n")
    with pytest.raises(OSError) as exc:
        raise_if_disk_full(log)
    assert exc.value.errno == errno.ENOSPC and str(log) in exc.value.filename
    log.write_text("poselib: Check failed: inliers > 0\n*** SIGABRT received\n")
    raise_if_disk_full(log)  # another failure: the next rung's to try
