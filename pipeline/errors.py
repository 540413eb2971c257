"""The error every stage raises on bad input: one line naming the file and the fix."""

from __future__ import annotations


class StageError(Exception):
    """A one-line, user-facing error (file + fix); the CLI prints it and exits with code 2."""
