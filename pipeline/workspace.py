"""The workspace: paths of every stage, and the up-to-date / resume bookkeeping.

A stage is up to date when its stamp (``.stages/<stage>.json``) records the same config hash, every
output it lists exists, and no input is newer than the stamp. Stages write their outputs first and the
stamp last, so a killed stage is never taken as done.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path


class StageError(Exception):
    """A one-line, user-facing error (file + fix); the CLI prints it and exits with code 2."""


class Workspace:
    def __init__(self, root: str | Path):
        self.root = Path(root).resolve()

    # paths of DESIGN.md
    @property
    def images(self) -> Path:
        return self.root / "images"

    @property
    def masks(self) -> Path:
        return self.root / "masks"

    @property
    def depth(self) -> Path:
        return self.root / "depth"

    @property
    def cameras(self) -> Path:
        return self.root / "cameras.npz"

    @property
    def model(self) -> Path:
        return self.root / "model"

    @property
    def mesh(self) -> Path:
        return self.root / "mesh"

    @property
    def stages(self) -> Path:
        return self.root / ".stages"

    def require(self, *paths: Path, hint: str) -> None:
        for p in paths:
            if not p.exists():
                raise StageError(f"{p}: missing; {hint}")

    # ------------------------------------------------------------------ stamps
    def _stamp(self, stage: str) -> Path:
        return self.stages / f"{stage}.json"

    def up_to_date(self, stage: str, cfg_hash: str, inputs: list[Path], outputs: list[Path]) -> bool:
        stamp = self._stamp(stage)
        if not stamp.exists():
            return False
        try:
            rec = json.loads(stamp.read_text())
        except (OSError, ValueError):
            return False
        if rec.get("config") != cfg_hash or not all(p.exists() for p in outputs):
            return False
        t = stamp.stat().st_mtime
        return all(newest_mtime(p) <= t for p in inputs)

    def mark_done(self, stage: str, cfg_hash: str, seconds: float, extra: dict | None = None) -> None:
        self.stages.mkdir(parents=True, exist_ok=True)
        rec = {"config": cfg_hash, "seconds": round(seconds, 3), "finished": time.time(), **(extra or {})}
        tmp = self._stamp(stage).with_suffix(".tmp")
        tmp.write_text(json.dumps(rec, indent=1))
        os.replace(tmp, self._stamp(stage))

    def stamp(self, stage: str) -> dict | None:
        """What a finished stage recorded (its config hash, seconds and details), or None."""
        try:
            return json.loads(self._stamp(stage).read_text())
        except (OSError, ValueError):
            return None

    def clear(self, stage: str) -> None:
        self._stamp(stage).unlink(missing_ok=True)

    def seconds(self) -> dict[str, float]:
        out = {}
        for p in sorted(self.stages.glob("*.json")) if self.stages.exists() else []:
            try:
                out[p.stem] = json.loads(p.read_text())["seconds"]
            except (OSError, ValueError, KeyError):
                pass
        return out


def newest_mtime(p: Path) -> float:
    """Newest modification time of a file or of anything inside a folder (0 when missing)."""
    if not p.exists():
        return 0.0
    if p.is_file():
        return p.stat().st_mtime
    m = p.stat().st_mtime
    for q in p.rglob("*"):
        if q.is_file():
            m = max(m, q.stat().st_mtime)
    return m


def subset_workspace(full: Path, dst: Path, keep: list[int]) -> None:
    """A new workspace ``dst`` of views ``keep`` (indices into ``full``'s sorted images): their images, masks and
    sparse depth, and the cameras renumbered (scale_mat and the support plane kept) — to hold photos out of
    training after SfM and the masks saw them all."""
    import shutil

    import numpy as np

    from dvr.data import list_images

    names = [p.stem for p in list_images(Path(full) / "images")]
    for sub in ("images", "masks", "depth"):
        (Path(dst) / sub).mkdir(parents=True)
        for i in keep:
            for f in (Path(full) / sub).glob(f"{names[i]}.*"):
                shutil.copy2(f, Path(dst) / sub / f.name)
    z = np.load(Path(full) / "cameras.npz")
    extra = {k: z[k] for k in ("scale_mat", "ground_plane") if k in z.files}
    np.savez(Path(dst) / "cameras.npz", **extra, **{f"{k}_{j}": z[f"{k}_{i}"] for j, i in enumerate(keep)
                                                    for k in ("world_mat", "scale_mat", "camera_mat")})
