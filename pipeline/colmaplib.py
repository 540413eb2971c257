"""pycolmap as this package uses it: every module imports it from here (``from .colmaplib import pycolmap``).

Loading it here does two things once per process. OpenCV is loaded first (by ``pipeline/__init__``, which runs
before any module of the package: pycolmap loaded before OpenCV makes OpenCV's PNG writer abort). And COLMAP's
logger (glog) writes no log files: by default it leaves a set of them for every process in the system's temporary
folder (``/tmp/<host>.<user>.log.INFO.<date>.<pid>`` and one per warning level), outside the workspace and never
removed. Its info lines are kept off the terminal (:func:`warnings_only`; warnings and errors still reach it), but
pycolmap's bundle adjustment turns them back on at every call and logs its own header whatever they are, so the
code that runs one in this process runs it inside :func:`quiet` and calls :func:`warnings_only` again before
COLMAP's next chatty step (the undistortion's two lines per photo). The SfM
rungs' child processes put the info lines back (:func:`info_to_stderr`): their output is the rung's log in the
workspace.
"""

from __future__ import annotations

import contextlib
import os
import sys

import pycolmap  # after OpenCV: this module's package, pipeline/__init__, loaded it

for _level in (pycolmap.logging.INFO, pycolmap.logging.WARNING, pycolmap.logging.ERROR, pycolmap.logging.FATAL):
    pycolmap.logging.set_log_destination(_level, "")  # no log files


PAIR_ID_BASE = 2147483647
"""COLMAP's database pair id: ``image_id1 * PAIR_ID_BASE + image_id2`` with ``image_id1 < image_id2``."""


def pair_images(pair_id: int) -> tuple[int, int]:
    """The two image ids of a COLMAP database pair id (the smaller first)."""
    return pair_id // PAIR_ID_BASE, pair_id % PAIR_ID_BASE


def warnings_only() -> None:
    """COLMAP's warnings and errors to stderr, its info lines nowhere."""
    pycolmap.logging.alsologtostderr = False
    pycolmap.logging.stderrthreshold = int(pycolmap.logging.WARNING)


@contextlib.contextmanager
def quiet():
    """COLMAP's lines off this process' stderr while the block runs: pycolmap's bundle adjustment logs its header and
    timing at info level whatever the logger's settings (it sets them itself). The file descriptor is redirected,
    so Python's exceptions still reach the user after the block."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def info_to_stderr() -> None:
    """COLMAP's info lines to this process' stderr too (a child whose output is a log file); still no log files."""
    pycolmap.logging.alsologtostderr = True


warnings_only()


def write_model(rec, folder) -> None:
    """``rec`` written to the folder ``folder`` whole or not at all: into a temporary folder beside it, checked for a
    full disk (:func:`dvr.atomic.check_room`: COLMAP's writer says nothing when the disk fills, it leaves the files
    cut short), then moved into place (a model already there is replaced)."""
    from dvr.atomic import atomic_path, check_room

    with atomic_path(folder, folder=True) as tmp:
        rec.write(tmp)
        check_room(tmp)


def raise_if_disk_full(log) -> None:
    """An OSError (ENOSPC) naming the COLMAP child's ``log`` when it says the disk filled (COLMAP's or SQLite's words,
    or a Python OSError's): that rung failed for want of space, which no other rung has either."""
    import errno
    import os
    from pathlib import Path

    from dvr.atomic import DISK_FULL_WORDS

    try:
        text = Path(log).read_text(errors="replace")
    except OSError:
        return
    if any(w in text for w in DISK_FULL_WORDS):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), f"{Path(log).parent} (COLMAP's log: {log})")
