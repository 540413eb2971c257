"""Messages a person reads: short lists (five names, not fifty), an object's size, a progress line while long
work runs."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from pathlib import Path

PROGRESS_EVERY = 20.0
"""Seconds between two progress lines of long work."""
LIST_LIMIT = 5
"""Names a message lists; more become their count and where to look."""


def names_or_count(names: Iterable[str], noun: str = "photos", look: Path | str | None = None) -> str:
    """``a, b, c`` for up to :data:`LIST_LIMIT` names; more: their count, the first three and where to look
    (``look``: a folder of overlays, a file listing them all)."""
    names = list(names)
    if len(names) <= LIST_LIMIT:
        return ", ".join(names)
    first = ", ".join(names[:3])
    return f"{len(names)} {noun} ({first}, …{f'; see {look}' if look else ''})"


def size_in_words(size: dict, metric: bool) -> str:
    """The object's size for a person: millimetres (height × width × depth) when the mesh is in metres (``metric``:
    a printed board set the scale), else that its scale is arbitrary."""
    if not metric:
        return ("the scale is arbitrary (no printed board was seen: docs/capture.md shows how one gives the mesh its "
                "size in metres)")
    return (f"{1000 * size['height']:.0f} × {1000 * size['width']:.0f} × {1000 * size['depth']:.0f} mm "
            "(height × width × depth, from the printed board)")


def say_now(line: str) -> None:
    """Print a progress line at once (stdout may be a file, block-buffered), in one write: lines from threads working
    side by side do not run into each other."""
    print(line + "\n", end="", flush=True)


def minutes(seconds: float) -> str:
    """``42 s``, ``3 min 05 s``."""
    s = int(round(seconds))
    return f"{s} s" if s < 60 else f"{s // 60} min {s % 60:02d} s"


@contextmanager
def heartbeat(what: str, every: float = PROGRESS_EVERY, say: Callable[[str], None] = say_now):
    """While the block runs, ``say`` ``what`` and the time it has taken every ``every`` seconds (a step that reports
    nothing itself: a call into COLMAP, a texture's bake; their native code lets this thread run)."""
    stop, t0 = threading.Event(), time.time()

    def beat() -> None:
        while not stop.wait(every):
            say(f"{what} ({minutes(time.time() - t0)})")

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
