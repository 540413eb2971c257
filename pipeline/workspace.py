"""The workspace: paths of every stage, and the up-to-date / resume bookkeeping.

A stage is up to date when its stamp (``.stages/<stage>.json``) records the same config hash, every
output it lists exists, and no input is newer than the stamp. Stages write their outputs first and the
stamp last, so a killed stage is never taken as done. A stage that starts writes ``.stages/<stage>.unfinished``
and removes it with its stamp: while it is there, the stage's outputs are those of an older run or half written
(a run that failed or was killed), and later stages refuse to read them. A run that fails having changed none of
its outputs (bad input found first) leaves stamp and marker as it found them. Every file is written atomically
(:mod:`dvr.atomic`: whole or absent, never half written), and one run at a time works in a workspace
(:mod:`pipeline.lock`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dvr.atomic import save_npz, write_bytes, write_json, write_text
from pipeline.errors import StageError


class Workspace:
    """A reconstruction's folder: the paths every stage reads and writes (docs/design.md, "Workspace"), and the
    stamps that make stages resumable and idempotent."""

    def __init__(self, root: str | Path):
        self.root = Path(root).resolve()

    @property
    def images(self) -> Path:
        """Training images written by the cameras stage (upright, resized)."""
        return self.root / "images"

    @property
    def masks(self) -> Path:
        """Object masks (white = object), one PNG per image."""
        return self.root / "masks"

    @property
    def depth(self) -> Path:
        """Sparse depth per view (depth/<view>.npz)."""
        return self.root / "depth"

    @property
    def sfm_model(self) -> Path:
        """The cameras stage's undistorted SfM model (none with given cameras that were not triangulated, or poses
        from a board)."""
        return self.root / "sfm" / "undistorted" / "sparse"

    @property
    def exposure(self) -> Path:
        """Per-view exposure gains measured on the SfM points by the cameras stage (pipeline/scene/exposure.py)."""
        return self.root / "exposure.json"

    @property
    def cameras(self) -> Path:
        """Cameras of every image (IDR/DVR convention; docs/design.md, Conventions)."""
        return self.root / "cameras.npz"

    @property
    def model(self) -> Path:
        """Checkpoints, log, appearance and the final model of the train stage."""
        return self.root / "model"

    @property
    def mesh(self) -> Path:
        """Raw, clean and textured meshes."""
        return self.root / "mesh"

    @property
    def stages(self) -> Path:
        """Stamps of the finished stages (<stage>.json)."""
        return self.root / ".stages"

    def make_root(self) -> None:
        """Create the workspace folder (StageError naming it when it is a file or cannot be created)."""
        if self.root.exists() and not self.root.is_dir():
            raise StageError(f"{self.root}: a file, not a workspace folder; give a new or existing folder")
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            probe = self.root / ".write-test"
            probe.touch()
            probe.unlink()
        except OSError as exc:
            raise StageError(f"{self.root}: cannot write the workspace here ({exc.strerror or type(exc).__name__}); "
                             "give a folder you can write to") from exc

    def require(self, *paths: Path, hint: str) -> None:
        """StageError naming the first missing path and ``hint`` (what to run first)."""
        for p in paths:
            if not p.exists():
                raise StageError(f"{p}: missing; {hint}")

    # ------------------------------------------------------------------ stamps
    def _stamp(self, stage: str) -> Path:
        return self.stages / f"{stage}.json"

    def _unfinished(self, stage: str) -> Path:
        return self.stages / f"{stage}.unfinished"

    def up_to_date(self, stage: str, cfg_hash: str, inputs: list[Path], outputs: list[Path]) -> bool:
        """Whether ``stage`` finished with this config hash, its outputs exist and no input is newer than its stamp."""
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
        """Write the stage's stamp (atomically, after its outputs): config hash, seconds and details."""
        self.stages.mkdir(parents=True, exist_ok=True)
        rec = {"config": cfg_hash, "seconds": round(seconds, 3), "finished": time.time(), **(extra or {})}
        write_json(self._stamp(stage), rec, indent=1)
        self._unfinished(stage).unlink(missing_ok=True)

    def stamp(self, stage: str) -> dict | None:
        """What a finished stage recorded (its config hash, seconds and details), or None."""
        try:
            return json.loads(self._stamp(stage).read_text())
        except (OSError, ValueError):
            return None

    def begin(self, stage: str, outputs: list[Path]) -> Before:
        """A run of ``stage`` starts: its stamp goes (while it runs it is not done) and ``<stage>.unfinished`` marks its
        outputs as not to be read until :meth:`mark_done`. Returns what :meth:`undo_begin` needs."""
        stamp, marker = self._stamp(stage), self._unfinished(stage)
        found = stamp.is_file()
        before = Before(stamp.read_bytes() if found else None, stamp.stat().st_mtime if found else 0.0,
                        marker.exists(), outputs_state(outputs))
        self.stages.mkdir(parents=True, exist_ok=True)
        write_text(marker, f"started {time.strftime('%Y-%m-%d %H:%M:%S')}\n")  # first: a full disk changes nothing
        stamp.unlink(missing_ok=True)
        return before

    def undo_begin(self, stage: str, outputs: list[Path], before: Before) -> None:
        """After a run of ``stage`` that failed: when it changed none of its ``outputs``, its stamp and marker as
        they were before :meth:`begin` (the stamp with its time: what was up to date still is)."""
        if outputs_state(outputs) != before.outputs:
            return
        stamp = self._stamp(stage)
        if before.stamp is not None:
            try:
                write_bytes(stamp, before.stamp)
                os.utime(stamp, (before.stamp_mtime, before.stamp_mtime))
            except OSError:  # no room for it (a full disk): the stage is not done, its marker stays, it runs again
                return
        if not before.unfinished:
            self._unfinished(stage).unlink(missing_ok=True)

    def unfinished(self, stage: str) -> bool:
        """Whether the last run of ``stage`` started and did not finish (it failed, or was stopped or killed)."""
        return self._unfinished(stage).exists()

    def seconds(self) -> dict[str, float]:
        """Seconds of every finished stage, by name."""
        out = {}
        for p in sorted(self.stages.glob("*.json")) if self.stages.exists() else []:
            try:
                out[p.stem] = json.loads(p.read_text())["seconds"]
            except (OSError, ValueError, KeyError):
                pass
        return out


@dataclass
class Before:
    """A stage's stamp (bytes and time), marker and outputs (:func:`outputs_state`) as a run found them."""

    stamp: bytes | None
    stamp_mtime: float
    unfinished: bool
    outputs: list[tuple]


def config_hash(obj) -> str:
    """Stable hash of a stage config (for the up-to-date check)."""
    d = dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class Sources:
    """Paths a user gives a run besides the workspace; read, never modified."""

    images: Path | None = None
    """Folder of photos, or a video file (MP4, MOV, …: its sharpest frames are taken)."""
    masks_dir: Path | None = None
    """Folder of your masks (white = object), named like the photos; automatic masks without it."""
    given_cameras: Path | None = None
    """Cameras instead of SfM: an IDR/DVR/NeuS cameras.npz (a world_mat_i per photo, sorted) or a COLMAP model."""


@dataclass
class Job:
    """One run of one stage: its workspace, its config section, the user's sources and the bookkeeping's verdict."""

    ws: Workspace
    """The workspace."""
    cfg: Any
    """The stage's config section (None for a stage without options)."""
    sources: Sources = field(default_factory=Sources)
    """Photos, user masks, given cameras."""
    force: bool = False
    """Redo the stage even when up to date (the train stage also discards its checkpoint)."""
    config_hash: str = "-"
    """Hash of the config section and the sources the stage reads (its stamp records it)."""
    inputs: list[Path] = field(default_factory=list)
    """The paths whose modification makes the stage stale (its row's ``inputs``)."""
    stop_after: int | None = None
    """Train stage: stop after this many steps without finishing (tests of resuming); None: run to the end."""
    stage_order: tuple[str, ...] = ()
    """The names of every stage in the order :func:`pipeline.stages.reconstruct` runs them (the report's table)."""


@dataclass
class Done:
    """What a finished stage body returns: the details its stamp records, and its seconds (None: the wall time of
    the body, measured by :func:`pipeline.stages.run_stage`)."""

    details: dict = field(default_factory=dict)
    seconds: float | None = None


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


def outputs_state(outputs: list[Path]) -> list[tuple]:
    """Per output path, what a run that wrote it changes: whether it exists and, for the file or each file in the
    folder, its name, modification time (ns), size and inode. The time alone misses a rewrite within the file
    system's time resolution (2 s on FAT, 1 s on some network shares); one that also keeps the size and the inode
    (an in-place rewrite of the same length) is still missed."""
    def files(p: Path) -> list[Path]:
        return [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else []

    def signature(q: Path, root: Path) -> tuple:
        st = q.stat()
        return q.relative_to(root).as_posix(), st.st_mtime_ns, st.st_size, st.st_ino

    return [(p.exists(), tuple(signature(q, p) for q in files(p))) for p in outputs]


def subset_workspace(full: Path, dst: Path, keep: list[int]) -> None:
    """A new workspace ``dst`` of views ``keep`` (indices into ``full``'s sorted images): their images, masks and
    sparse depth and exposure, the cameras renumbered (scale_mat and the support plane kept) and the SfM points — to
    hold photos out of training after SfM and the masks saw them all."""
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
    save_npz(Path(dst) / "cameras.npz", **extra, **{f"{k}_{j}": z[f"{k}_{i}"] for j, i in enumerate(keep)
                                                    for k in ("world_mat", "scale_mat", "camera_mat")})
    if (Path(full) / "points.ply").exists():
        shutil.copy2(Path(full) / "points.ply", Path(dst) / "points.ply")
    if Workspace(full).exposure.exists():  # the photos' gains, of the views kept
        from pipeline.scene.exposure import read_exposure, write_exposure

        write_exposure(Workspace(dst).exposure, read_exposure(Workspace(full).exposure, [names[i] for i in keep]))
