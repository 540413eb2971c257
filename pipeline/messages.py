"""Messages a person reads: short lists (five names, not fifty), an object's size."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

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
