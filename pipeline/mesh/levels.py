"""Detail levels: the clean mesh at the face budgets people ship (Apple's Object Capture's: preview under 25 k
triangles, reduced 50 k, medium 100 k, full 250 k, raw not decimated), written beside the default mesh from the same
training (``--mesh.detail medium,preview``)."""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import StageError

LEVELS: dict[str, int | None] = {"preview": 25_000, "reduced": 50_000, "medium": 100_000, "full": 250_000,
                                 "raw": None}
"""Face budget of each detail level (None: the clean mesh as extracted, not decimated)."""


def parse_levels(text: str) -> list[str]:
    """The levels named in ``--mesh.detail`` (comma-separated, in the order given, each once; empty: none); a
    StageError naming the option and the levels for an unknown one."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in LEVELS]
    if unknown:
        raise StageError(f"--mesh.detail: unknown level '{unknown[0]}'; use one or more of "
                         f"{', '.join(LEVELS)}, comma-separated (e.g. medium,preview)")
    return list(dict.fromkeys(names))


def level_folder(mesh_dir: Path, level: str) -> Path:
    """Where a detail level's meshes go: ``mesh/levels/<level>/`` (clean.ply; the texture stage's textured.*)."""
    return mesh_dir / "levels" / level


def budget(level: str) -> int:
    """The level's face budget for the decimation (raw: no limit)."""
    faces = LEVELS[level]
    return faces if faces is not None else 2**31 - 1
