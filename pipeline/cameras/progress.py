"""Progress of an SfM child process, read from COLMAP's log as it grows: a line at least every
:data:`PROGRESS_EVERY` seconds (photos featured, blocks of pairs matched, photos registered), and its time budget."""

from __future__ import annotations

import re
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

from pipeline.messages import PROGRESS_EVERY, minutes, say_now

_STEPS: tuple[tuple[re.Pattern, Callable[[re.Match], str]], ...] = (
    (re.compile(r"Processed file \[(\d+)/(\d+)\]"), lambda m: f"features of {m[1]}/{m[2]} photos"),
    (re.compile(r"Processing block \[(\d+)/(\d+), (\d+)/(\d+)\]"),
     lambda m: f"matching, block {(int(m[1]) - 1) * int(m[4]) + int(m[3])}/{int(m[2]) * int(m[4])}"),
    (re.compile(r"Matching image \[(\d+)/(\d+)\]"), lambda m: f"matching, photo {m[1]}/{m[2]}"),
    (re.compile(r"Matching (\d+) pairs of similar photos"), lambda m: f"matching {m[1]} pairs of similar photos"),
    (re.compile(r"Processing block \[(\d+)/(\d+)\]"), lambda m: f"matching, block {m[1]}/{m[2]}"),
    (re.compile(r"Loading database"), lambda m: "mapping: loading the matches"),
    (re.compile(r"Finding good initial image pair"), lambda m: "mapping: choosing the first two photos"),
    (re.compile(r"num_reg_frames=(\d+)"), lambda m: f"mapping, {m[1]} photos registered"),
    (re.compile(r"Loading (\w+)\.\.\."), lambda m: f"mapping: loading the {m[1]}"),
    (re.compile(r"=== Reconstructing component (\d+) / (\d+) with (\d+) images"),
     lambda m: f"global mapping: part {m[1]}/{m[2]}, {m[3]} photos"),
    (re.compile(r"=== Running (.+?) ==="), lambda m: f"global mapping: {m[1]}"),
    (re.compile(r"Global bundle adjustment iteration (\d+) / (\d+)"),
     lambda m: f"global mapping: bundle adjustment, pass {m[1]}/{m[2]}"),
    (re.compile(r"\] Running (.+?)\.*\s*$"), lambda m: f"mapping: {m[1].lower()}"),
)


class LogProgress:
    """What a COLMAP child process is doing, from the lines its log gained since the last :meth:`update`."""

    def __init__(self, log: Path):
        self.log = log
        self._offset = 0
        self._partial = ""
        self.state = "starting"

    def update(self) -> str:
        """Read the log's new lines; returns the latest step found (the previous one when none is new)."""
        try:
            with open(self.log, "rb") as f:
                f.seek(self._offset)
                chunk = f.read()
        except OSError:
            return self.state
        self._offset += len(chunk)
        lines = (self._partial + chunk.decode("utf-8", "replace")).split("\n")
        self._partial = lines.pop()
        for line in lines:
            for pattern, say in _STEPS:
                m = pattern.search(line)
                if m:
                    self.state = say(m)
                    break
        return self.state


def wait_with_progress(p: subprocess.Popen, log: Path, label: str, stop_at: float | None,
                       say: Callable[[str], None] = say_now, every: float = PROGRESS_EVERY) -> bool:
    """Wait for the child ``p`` writing ``log``; every ``every`` seconds ``say`` a line of what it does (``label``:
    the rung). Kill it at ``stop_at`` (time.time(); None: never). Returns whether it was killed."""
    watch, t0 = LogProgress(log), time.time()
    last = t0
    while True:
        try:
            p.wait(timeout=min(1.0, every))
            return False
        except subprocess.TimeoutExpired:
            pass
        now = time.time()
        if stop_at is not None and now >= stop_at:
            p.kill()
            p.wait()
            return True
        if now - last >= every:
            say(f"cameras: rung {label}: {watch.update()} ({minutes(now - t0)})")
            last = now
