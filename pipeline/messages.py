"""Short lists in messages: a person reads five names, not fifty."""

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
