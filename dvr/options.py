"""Range rules declared on config fields: ``size: PositiveInt = 400``.

A field typed :data:`PositiveInt` or :data:`PositiveFloat` (or a tuple annotated with :data:`POSITIVE`) must be
above 0, one typed :data:`Fraction` within [0, 1]; every other number must be finite and ≥ 0 (a 0 there switches a
term or a step off). The types stay ``int`` and ``float`` for tyro, editors and type checkers;
``pipeline.config.check_config`` reads the markers.
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


class _Fraction:
    """The marker: the option is a share, from 0 to 1."""

    def __repr__(self) -> str:
        return "FRACTION"


FRACTION = _Fraction()
Fraction = Annotated[float, FRACTION]
"""A number from 0 to 1."""


def is_fraction(hint) -> bool:
    """Whether a type hint carries the :data:`FRACTION` marker."""
    return any(m is FRACTION for m in getattr(hint, "__metadata__", ()))


def is_positive(hint) -> bool:
    """Whether a type hint (read with ``typing.get_type_hints(..., include_extras=True)``) carries the marker."""
    return any(m is POSITIVE for m in getattr(hint, "__metadata__", ()))
