"""Range rules declared on config fields: ``size: PositiveInt = 400``.

A field typed :data:`PositiveInt` or :data:`PositiveFloat` (or a tuple annotated with :data:`POSITIVE`) must be
above 0; every other number must be finite and ≥ 0 (a 0 there switches a term or a step off). The types stay
``int`` and ``float`` for tyro, editors and type checkers; ``pipeline.config.check_config`` reads the marker.
"""

from __future__ import annotations

from typing import Annotated


class _Positive:
    """The marker: the option must be above 0 (sizes, counts, resolutions, scales)."""

    def __repr__(self) -> str:
        return "POSITIVE"


POSITIVE = _Positive()
PositiveInt = Annotated[int, POSITIVE]
"""A whole number ≥ 1."""
PositiveFloat = Annotated[float, POSITIVE]
"""A finite number > 0."""


def is_positive(hint) -> bool:
    """Whether a type hint (read with ``typing.get_type_hints(..., include_extras=True)``) carries the marker."""
    return any(m is POSITIVE for m in getattr(hint, "__metadata__", ()))
