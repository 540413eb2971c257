"""The pipeline API: the stage table, :func:`run_stage` and :func:`reconstruct`.

Every caller drives stages through here: the CLI (``python -m pipeline <stage>``, ``python -m pipeline
reconstruct``), ``make reconstruct``, the tests and the bench. A stage is one row of :data:`STAGES`: its name, its
options (a config dataclass, which becomes the field ``<name>`` of :class:`pipeline.config.Config` and the CLI
namespace ``--<name>.*``), its body (the stage module's ``run(job)``), what it requires, what makes it stale and
what it writes. Adding a stage is adding its row (and its module). :func:`run_stage` owns the bookkeeping every
stage shares (require the inputs, and their stage finished; skip when up to date; mark the stage begun; time the
body; stamp it done); the bodies only work.
See docs/design.md, "Stage contracts".

    from pipeline.stages import reconstruct, run_stage
    from pipeline.config import load_config

    cfg = load_config("configs/fast.yaml")
    reconstruct("photos/", "work/vase", cfg)            # every stage, each skipped when up to date
    run_stage("texture", "work/vase", cfg, force=True)  # one stage again
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from dvr.atomic import is_disk_full
from dvr.config import TrainConfig
from pipeline.cameras import stage as cameras
from pipeline.cameras.config import CamerasConfig
from pipeline.config import Config, check_config
from pipeline.depth import stage as depth
from pipeline.depth.config import DepthConfig
from pipeline.errors import StageError
from pipeline.lock import workspace_lock
from pipeline.masks import stage as masks
from pipeline.masks.config import MasksConfig
from pipeline.mesh import stage as mesh
from pipeline.mesh.config import MeshConfig
from pipeline.report import stage as report
from pipeline.texture import stage as texture
from pipeline.texture.config import TextureConfig
from pipeline.train import stage as train
from pipeline.workspace import Done, Job, Sources, Workspace, config_hash

Paths = Callable[[Workspace], list[Path]]


@dataclass(frozen=True)
class Stage:
    """One row of the stage table."""

    name: str
    """Command name (``python -m pipeline <name>``, ``make <name>``) and stamp name (``.stages/<name>.json``)."""
    summary: str
    """One line for ``--help``: what it does, reads and writes."""
    body: Callable[[Job], Done | None]
    """The stage's work (its module's ``run``): None when it stopped early on request (training's ``stop_after``)."""
    options: type | None
    """Its config dataclass (field ``<name>`` of :class:`~pipeline.config.Config`, CLI options ``--<name>.*``, YAML
    section ``<name>:``); None: no options."""
    requires: Callable[[Workspace], list[tuple[Path, str]]]
    """Paths that must exist, each with the stage that writes it (named in the error)."""
    inputs: Callable[[Workspace, Sources], list[Path]]
    """Paths whose modification makes the stage stale (missing ones are ignored)."""
    outputs: Paths
    """Paths the stage writes; the first is shown as its product. All must exist for it to be up to date."""
    sources: tuple[str, ...] = ()
    """Fields of :class:`~pipeline.workspace.Sources` it reads (CLI options; part of its config hash)."""
    from_photos: bool = False
    """:func:`reconstruct` runs it only when given photos or one of its own ``sources``: a workspace made by
    ``python -m synth`` already has its images, masks and cameras."""
    always: bool = False
    """Run even when up to date (the report: cheap, and it shows the latest state)."""
    check: Callable[[Workspace, Sources], None] | None = None
    """Checks of the user's sources before anything else (StageError on bad input)."""

    @property
    def section(self) -> str | None:
        """Its field of :class:`~pipeline.config.Config` (its name), None without options."""
        return self.name if self.options is not None else None


def _if_there(path: Path) -> list[Path]:
    """[path] when it exists (an optional input), else []."""
    return [path] if path.exists() else []


def _photos_outside_workspace(ws: Workspace, src: Sources) -> None:
    """The cameras stage needs photos, and a workspace that is neither the photo folder nor inside it."""
    if src.images is None:
        raise StageError(f"{ws.root}: the cameras stage needs --images DIR (the photos)")
    if ws.root == src.images or src.images in ws.root.parents:
        raise StageError(f"{ws.root}: the workspace must not be the photo folder or inside it; choose another OUT")


def _mask_files(ws: Workspace) -> list[Path]:
    from dvr.data import list_images

    return [ws.masks] + [ws.masks / f"{p.stem}.png" for p in list_images(ws.images)]


STAGES: tuple[Stage, ...] = (
    Stage("cameras", "Estimate cameras with COLMAP (reads the photos; writes sfm/, images/, cameras.npz, points.ply, "
          "exposure.json).",
          cameras.run, CamerasConfig,
          requires=lambda ws: [],
          inputs=lambda ws, src: [p for p in (src.images, src.given_cameras) if p is not None],
          outputs=lambda ws: [ws.cameras, ws.images, ws.root / "points.ply"]
          + ([ws.exposure] if ws.sfm_model.exists() else []),  # measured on the SfM points
          sources=("images", "given_cameras"), from_photos=True, check=_photos_outside_workspace),
    Stage("masks", "Object masks (reads images/, cameras.npz, sfm/, exposure.json; writes masks/*.png, "
          "masks/overlays/, masks/confidence.json).", masks.run, MasksConfig,
          requires=lambda ws: [(ws.images, "cameras"), (ws.cameras, "cameras")],
          inputs=lambda ws, src: [ws.images, ws.cameras] + ([src.masks_dir] if src.masks_dir else [])
          + _if_there(ws.exposure),
          outputs=_mask_files, sources=("masks_dir",), from_photos=True),
    Stage("depth", "Sparse depth from the SfM tracks (reads sfm/, cameras.npz; writes depth/*.npz).",
          depth.run, DepthConfig,
          requires=lambda ws: [(ws.images, "cameras"), (ws.cameras, "cameras")],
          inputs=lambda ws, src: [ws.cameras, ws.root / "sfm"],
          outputs=lambda ws: [ws.depth] if ws.sfm_model.exists() else [], from_photos=True),
    Stage("train", "Train the DVR occupancy and texture fields (reads images/, masks/, depth/, cameras.npz, "
          "exposure.json; writes model/).", train.run, TrainConfig,
          requires=lambda ws: [(ws.images, "cameras"), (ws.masks, "masks"), (ws.cameras, "cameras")],
          inputs=lambda ws, src: [ws.images, ws.masks, ws.cameras] + _if_there(ws.depth) + _if_there(ws.exposure),
          outputs=lambda ws: [ws.model / "final.pt"]),
    Stage("mesh", "Extract and clean the mesh (reads model/, points.ply, with --mesh.drop-unseen cameras.npz; writes "
          "mesh/raw.ply and mesh/clean.ply).",
          mesh.run, MeshConfig,
          requires=lambda ws: [(ws.model / "final.pt", "train")],
          inputs=lambda ws, src: [ws.model / "final.pt", ws.root / "points.ply", ws.cameras],
          outputs=lambda ws: [ws.mesh / "clean.ply", ws.mesh / "raw.ply"]),
    Stage("texture", "UV-texture the clean mesh from the photos (reads mesh/clean.ply, model/, images/, "
          "cameras.npz; writes mesh/textured.obj/.mtl/.png, .glb and .usdz, and the normal and occlusion maps).",
          texture.run, TextureConfig,
          requires=lambda ws: [(ws.mesh / "clean.ply", "mesh"), (ws.images, "cameras"), (ws.cameras, "cameras")],
          inputs=lambda ws, src: [ws.mesh / "clean.ply", ws.images, ws.cameras, ws.model / "final.pt",
                                  ws.model / "appearance.json"],
          outputs=lambda ws: [ws.mesh / f"textured.{e}" for e in ("glb", "obj", "mtl", "png", "usdz")]),
    Stage("report", "Write report.html: stage times, SfM summary, mask overlays, curves, renders, interactive "
          "mesh viewer.", report.run, None,
          requires=lambda ws: [(ws.root, "cameras")],
          inputs=lambda ws, src: [],
          outputs=lambda ws: [ws.root / "report.html"], always=True),
)
"""The stages in the order :func:`reconstruct` runs them."""


def stage_named(name: str) -> Stage:
    """The row of :data:`STAGES` called ``name`` (ValueError naming the stages otherwise)."""
    for stage in STAGES:
        if stage.name == name:
            return stage
    raise ValueError(f"{name}: no such stage; stages: {', '.join(s.name for s in STAGES)}")


def _sources(stage: Stage, images=None, masks_dir=None, given_cameras=None) -> Sources:
    given = {"images": images, "masks_dir": masks_dir, "given_cameras": given_cameras}
    unused = [k for k, v in given.items() if v is not None and k not in stage.sources]
    if unused:
        raise ValueError(f"stage {stage.name} takes no {', '.join(unused)}")
    return Sources(**{k: Path(v).resolve() if v is not None else None for k, v in given.items()})


@dataclass
class _Plan:
    """What a stage call resolves before deciding anything: the row, workspace, config section, sources, hash."""

    stage: Stage
    ws: Workspace
    cfg: object
    src: Sources
    config_hash: str


def _plan(name: str, workspace, config, images, masks_dir, given_cameras) -> _Plan:
    stage = stage_named(name)
    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    src = _sources(stage, images, masks_dir, given_cameras)
    cfg = getattr(config or Config(), stage.section) if stage.section else None
    h = config_hash({"cfg": dataclasses.asdict(cfg) if cfg is not None else None,
                     **{k: str(getattr(src, k)) for k in stage.sources}})
    return _Plan(stage, ws, cfg, src, h)


def is_up_to_date(name: str, workspace: str | Path | Workspace, config: Config | None = None, *,
                  images: str | Path | None = None, masks_dir: str | Path | None = None,
                  given_cameras: str | Path | None = None) -> bool:
    """Whether :func:`run_stage` with these arguments would skip stage ``name`` (an ``always`` stage: whether it
    has run once)."""
    p = _plan(name, workspace, config, images, masks_dir, given_cameras)
    if p.stage.always:
        return p.ws.stamp(name) is not None
    if not all(path.exists() for path, _ in p.stage.requires(p.ws)):
        return False
    return p.ws.up_to_date(name, p.config_hash, p.stage.inputs(p.ws, p.src), p.stage.outputs(p.ws))


def run_stage(name: str, workspace: str | Path | Workspace, config: Config | None = None, force: bool = False, *,
              images: str | Path | None = None, masks_dir: str | Path | None = None,
              given_cameras: str | Path | None = None, stop_after: int | None = None) -> bool:
    """Run stage ``name`` in ``workspace`` with ``config`` (defaults without one) unless it is up to date;
    returns whether it ran. ``images``, ``masks_dir`` and ``given_cameras`` are the user's paths for the stages that
    read them; ``stop_after`` stops training early (tests of resuming). Raises StageError (one line: the file and
    the fix) on bad input."""
    p = _plan(name, workspace, config, images, masks_dir, given_cameras)
    if p.cfg is not None:
        check_config(p.cfg, p.stage.section + ".", here=True)
    if p.stage.check is not None:  # before the lock: a workspace inside the photos gets nothing written
        p.stage.check(p.ws, p.src)
    # the lock for the checks too (another run may be changing what they read); a workspace not made yet is locked
    # once the stage makes it
    lock = workspace_lock(p.ws.root, f"the {name} stage", required=False) if p.ws.root.is_dir() else \
        contextlib.nullcontext()
    with disk_full_is_one_line(name, p.ws), lock:
        return _run_locked(p, force, stop_after)


def _run_locked(p: _Plan, force: bool, stop_after: int | None) -> bool:
    """:func:`run_stage` after its plan and checks, holding the workspace (or about to make it)."""
    stage, ws, name = p.stage, p.ws, p.stage.name
    for path, producer in stage.requires(ws):
        ws.require(path, hint=f"run the {producer} stage first")
        if ws.unfinished(producer) and path in stage_named(producer).outputs(ws):
            raise StageError(f"{path}: the {producer} stage's last run did not finish (it failed or was stopped), "
                             f"so this may be an older run's or half written; run the {producer} stage again")
    inputs, outputs = stage.inputs(ws, p.src), stage.outputs(ws)
    if not force and not stage.always and ws.up_to_date(name, p.config_hash, inputs, outputs):
        print(f"{name}: up to date ({outputs[0] if outputs else ws.root})")
        return False
    ws.make_root()  # only a stage that runs writes: a call with nothing to do leaves the workspace as it was
    with workspace_lock(ws.root, f"the {name} stage"):
        before = ws.begin(name, outputs)
        t0 = time.perf_counter()
        try:
            done = stage.body(Job(ws, p.cfg, p.src, force, p.config_hash, inputs, stop_after,
                                   tuple(s.name for s in STAGES)))
        except BaseException:  # a failure that wrote nothing (bad input found first) leaves the workspace as it was
            ws.undo_begin(name, outputs, before)
            raise
        if done is None:  # stopped early on request; the next run resumes
            return True
        seconds = done.seconds if done.seconds is not None else time.perf_counter() - t0
        ws.mark_done(name, p.config_hash, seconds, done.details)
    return True


def _size(n: float) -> str:
    """``n`` bytes in words (kB, MB, GB: powers of 1000)."""
    for unit in ("bytes", "kB", "MB"):
        if n < 1000:
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} GB"


def disk_full_message(name: str, ws: Workspace, exc: BaseException) -> str:
    """The one line of stage ``name`` stopped by a full disk or quota (``exc``, :func:`dvr.atomic.is_disk_full`):
    what it was writing (and its size when known), the space left on the workspace's disk, and what to do."""
    cause = exc
    while cause is not None and not (isinstance(cause, OSError) and cause.filename):
        cause = cause.__cause__ or cause.__context__
    path, size = getattr(cause, "filename", None), getattr(cause, "size", None)
    what = f"{path}{f' ({_size(size)})' if size else ''}" if path else "its files"
    try:
        free = f"{_size(shutil.disk_usage(ws.root).free)} free"
    except OSError:
        free = "free space unknown"
    quota = getattr(cause, "errno", None) == getattr(errno, "EDQUOT", -1)
    return (f"{name}: the {'disk quota' if quota else 'disk'} is full: no room to write {what}; {free} on the disk "
            f"of {ws.root}. Free some space and run the same command again: finished stages are kept")


@contextlib.contextmanager
def disk_full_is_one_line(name: str, ws: Workspace):
    """A full disk or quota inside the block (an OSError with ENOSPC or EDQUOT, or COLMAP's and SQLite's words for
    it) as stage ``name``'s one-line StageError (:func:`disk_full_message`). Every file is written atomically
    (:mod:`dvr.atomic`): what the stage had finished stays whole, its marker makes the next run redo it."""
    try:
        yield
    except StageError:
        raise
    except Exception as exc:
        if not is_disk_full(exc):
            raise
        raise StageError(disk_full_message(name, ws, exc)) from exc


def check_user_masks(images: str | Path, masks_dir: str | Path) -> None:
    """The user's ``masks_dir`` holds a mask for every photo of the folder ``images``
    (:func:`pipeline.masks.stage.mask_files`), checked before SfM runs, so that a missing mask is said at once, not
    after the cameras stage; StageError with the masks stage's own line otherwise. A video's frames are named only once
    extracted: nothing to check then."""
    if Path(images).is_dir():
        masks.mask_files([p.stem for p in cameras.list_photos(Path(images))[0]], Path(masks_dir))


def reconstruct(images: str | Path | None, workspace: str | Path, config: Config | None = None, *,
                masks_dir: str | Path | None = None, given_cameras: str | Path | None = None,
                force: bool = False) -> Path:
    """Every stage in order, each skipped when up to date (a killed run resumes where it stopped); returns the
    textured GLB. Without ``images`` the workspace must already hold images/, masks/ and cameras.npz (as
    ``python -m synth`` writes them); ``masks_dir`` gives user masks, ``given_cameras`` skips SfM (and needs
    ``images``)."""
    check_config(config or Config(), here=True)  # every stage's options before the first stage runs
    ws = Workspace(workspace)
    if images is None and not ws.cameras.exists():
        raise StageError(f"{ws.root}: no photos given and no cameras.npz there; pass the photo folder (--images DIR)")
    if images is not None:
        _photos_outside_workspace(ws, Sources(images=Path(images).resolve()))
    if masks_dir is not None and images is not None:
        check_user_masks(images, masks_dir)
    given = {"images": images, "masks_dir": masks_dir, "given_cameras": given_cameras}
    ws.make_root()
    # the workspace is this run's from the first stage to the last: no other run slips in between two stages
    with disk_full_is_one_line("reconstruct", ws), workspace_lock(ws.root, "reconstruct"):
        for stage in STAGES:
            # a stage of the photos runs when they are given or when any of its own sources is (user masks for a
            # workspace that holds images; given cameras without photos: the cameras stage says what is missing)
            if stage.from_photos and not any(given[k] is not None for k in stage.sources) and images is None:
                continue
            run_stage(stage.name, ws, config, force, **{k: given[k] for k in stage.sources})
    return ws.mesh / "textured.glb"
