"""The workspace lock: one run at a time writes a workspace.

A run (a stage command, ``reconstruct``, a batch's stage task) holds ``WS/.stages/lock`` while it works; a second
run on the same workspace stops at once with one line naming the first (:class:`WorkspaceBusy`: its PID, command
and start, how to wait for it). The lock is :class:`filelock.FileLock`, an ``flock`` the kernel releases when the
process ends however it ends, so a killed run never blocks the next one. Who holds it is recorded beside it in
``WS/.stages/lock.info`` (JSON, written atomically, removed on release): a run that finds that record but takes the
lock knows the run before it was killed, says so, and takes over (its stage's ``.unfinished`` marker makes the
stage run again).

The lock is re-entrant within a process (``reconstruct`` holds it and calls :func:`pipeline.stages.run_stage`
per stage, which takes it again). Its file descriptor is not inherited by child processes (Python opens files
non-inheritable), so a child such as the SfM rung's ``python -m pipeline.cameras.sfm`` neither holds nor takes it.
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import socket
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from filelock import FileLock, Timeout

from dvr.atomic import is_disk_full, sweep_partials, write_json
from pipeline.errors import StageError

_local = threading.local()  # per thread: the workspaces it holds and how many times


class WorkspaceBusy(StageError):
    """Another run holds the workspace (one line: who, and how to wait for it)."""


def lock_file(root: Path) -> Path:
    """The lock's file in the workspace ``root``."""
    return Path(root) / ".stages" / "lock"


def info_file(root: Path) -> Path:
    """The record of the run that holds the lock of the workspace ``root``."""
    return Path(root) / ".stages" / "lock.info"


def this_run(what: str) -> dict:
    """The record :func:`workspace_lock` writes for this process: PID, host, command line, what it runs, start."""
    argv = getattr(sys, "orig_argv", None) or [sys.executable, *sys.argv]
    command = " ".join(shlex.join([Path(argv[0]).name, *argv[1:]]).split())  # one line
    return {"pid": os.getpid(), "host": socket.gethostname(), "command": command[:300], "run": what,
            "started": time.strftime("%Y-%m-%d %H:%M:%S")}


def read_info(root: Path) -> dict | None:
    """The record of the run that holds (or last held, when it was killed) the workspace, or None."""
    try:
        rec = json.loads(info_file(root).read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) else None


def _who(rec: dict | None) -> str:
    if rec is None:
        return "another run (it is starting: no record yet)"
    host = f" on {rec.get('host')}" if rec.get("host") not in (None, socket.gethostname()) else ""
    return f"PID {rec.get('pid', '?')}{host}, {rec.get('command', '?')!r}, since {rec.get('started', '?')}"


def busy_message(root: Path, rec: dict | None) -> str:
    """The one line of a run refused because ``rec``'s run holds the workspace ``root``."""
    pid = rec.get("pid") if rec else None
    wait = f"wait for it to end (tail --pid={pid} -f /dev/null waits) and run again" if pid else \
        "wait for it to end and run again"
    return (f"{root}: another run is working in this workspace ({_who(rec)}); {wait}; if no such process runs "
            f"(a file system without locks kept it), delete {lock_file(root)}")


def _held() -> dict[Path, int]:
    """The workspaces this thread holds, each with how many blocks hold it."""
    if not hasattr(_local, "held"):
        _local.held = {}
    return _local.held


@contextlib.contextmanager
def workspace_lock(root: Path, what: str, required: bool = True) -> Iterator[None]:
    """Hold the lock of the workspace ``root`` (an existing folder) for the block; ``what`` says what this run does
    (recorded for a run that finds it busy). Raises :class:`WorkspaceBusy` at once when another run holds it.
    Re-entrant: a block inside a block of this thread on the same workspace holds it already. Not ``required``: a
    workspace where the lock's file cannot be made (read-only) is read without it (a run that writes takes it)."""
    root = Path(root).resolve()
    held = _held()
    if root in held:
        held[root] += 1
        try:
            yield
        finally:
            held[root] -= 1
        return
    lock = FileLock(lock_file(root))
    try:
        (root / ".stages").mkdir(exist_ok=True)
        lock.acquire(blocking=False)
    except Timeout:
        raise WorkspaceBusy(busy_message(root, read_info(root))) from None
    except OSError as exc:
        if required or is_disk_full(exc):
            raise
        lock = None  # a read-only workspace: read without the lock
    if lock is None:
        yield
        return
    try:
        before = read_info(root)
        if before is not None:  # a record left behind: its run was killed (the kernel released its lock)
            print(f"note: {root}: the run before ({_who(before)}) ended without releasing the workspace (killed?); "
                  "taking it over: a stage it left unfinished runs again", file=sys.stderr)
        swept = sweep_partials(root)  # what killed writers left: nobody else writes here now
        if swept:
            print(f"note: {root}: removed {swept} temporary file(s) of an interrupted write", file=sys.stderr)
        with contextlib.suppress(OSError):  # the record is a courtesy: a full disk must not stop the run here
            write_json(info_file(root), this_run(what), indent=1)
        held[root] = 1
        try:
            yield
        finally:
            del held[root]
            with contextlib.suppress(OSError):
                info_file(root).unlink()
    finally:
        lock.release()


def end_with_parent(parent: int) -> None:
    """In a child process of a run (the SfM rung's ``python -m pipeline.cameras.sfm``), ``parent`` the PID of the run
    that started it: end when the run's process ends, however it ends (Linux's parent-death signal; elsewhere
    nothing), so that a killed run leaves no child writing in a workspace whose lock the kernel has released for the
    next run. A run that died before this call (while the child was still importing) has left the child to another
    parent: it ends at once."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:
        os._exit(1)
