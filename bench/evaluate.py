"""One benchmark run (in its own process): a synthetic scene or DTU through the same CLI a user runs, measured.

Synthetic scenes, GT cameras: the scene's images, GT masks and cameras go straight to training. Synthetic scenes
and DTU through SfM ("photos only"): the training AND held-out photos go through cameras → masks → depth together
(as a user's folder would; the standard protocol of NeRF-style evaluations on COLMAP poses), training sees the
training views only, and the textured mesh is rendered at the poses SfM gave the held-out photos. For synthetic
scenes the held-out PSNR at the GT poses (mapped into the SfM frame by a Sim(3) of the camera centres, with SfM's
focal length) is kept too: it adds the pose error to the picture. Every row also gives it re-aimed
(:mod:`bench.reaim`): each held-out view turned about its centre onto its photo, the mesh frozen (the test-time
pose alignment of methods with estimated cameras), which takes SfM's error in the held-out photos' own poses out of
the figure. Geometry: Chamfer and F-score@1 % of the GT diagonal after that Sim(3); automatic masks: IoU against
the GT masks.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline.workspace import subset_workspace

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "bench" / "runs"
DTU = ROOT.parent / "shared" / "data" / "dtu_scan24"
REAL = {"mouse": DTU.parent / "mouse_phone", "blowtorch": DTU.parent / "blowtorch"}
"""Real captures run from their photos alone (:func:`run_real`): a phone's white-on-white mouse, a shiny blowtorch on a
carpet (with hand masks); DTU scan24 has its own row (:func:`run_dtu`)."""
FOLDERS = {"mouse24": ("mouse", 24, 4032)}
"""Phone folders made from a real capture's photos (:func:`take_photos`): (capture of :data:`REAL`,
photos taken evenly spaced, longest side): 24 of the mouse's photos at a 12 MP phone's 4032×3024."""
SCENES = {
    "cow": ROOT / "configs" / "scenes" / "cow_floor.yaml",
    "jar": ROOT / "configs" / "scenes" / "jar_floor.yaml",
    "book": ROOT / "configs" / "scenes" / "book_floor.yaml",
    "jar_alike": ROOT / "configs" / "scenes" / "jar_table_alike.yaml",  # the jar on a table of its own colours
    "stool": ROOT / "configs" / "scenes" / "stool_floor.yaml",  # a plain stool, legs 0.85 of its height, floor-coloured
    "mug": ROOT / "configs" / "scenes" / "mug_table.yaml",  # an open mug, its handle's hole showing the table
    "thin": ROOT / "configs" / "scenes" / "thin_plate.yaml",  # a 0.04-thick plate on a sphere (not a bench row)
    "cow_float": ROOT / "configs" / "scenes" / "cow_backdrop.yaml",
    "sphere": ROOT / "configs" / "scenes" / "sphere_checker.yaml",
    "torus_board": ROOT / "configs" / "scenes" / "torus_board.yaml",
    "sphere_board": ROOT / "configs" / "scenes" / "sphere_checker_board.yaml",
    "e2e": ROOT / "configs" / "scenes" / "e2e_floor.yaml",  # the small torus on a floor (bench/batch.py)
    "white_table": ROOT / "configs" / "scenes" / "white_table.yaml",  # a puck on a white table: no SfM points on it
    "knobbly": ROOT / "configs" / "scenes" / "knobbly_ball.yaml",  # bumps finer than 25 000 faces hold (normal maps)
}
HELDOUT = "heldout_"
"""Prefix of the held-out photos in a photos-only run's folder (sorted after the training photos)."""


def fresh_folder(path: Path) -> Path:
    """``path`` emptied (removed and made again): a run's work folder."""
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    return path


def scene(name: str, over: dict) -> Path:
    """Render (once, cached in bench/runs/scenes) the synthetic scene with overrides; returns its folder."""
    import yaml

    from synth import scene_from_dict, write_scene

    tag = name + ("-" + "-".join(f"{k}{sorted(v.items()) if isinstance(v, dict) else v}" for k, v in over.items())
                  if over else "")
    tag = "".join(c if c.isalnum() or c in "-_" else "_" for c in tag)
    out = RUNS / "scenes" / tag
    if not (out / "gt" / "scene.json").exists():
        d = yaml.safe_load(SCENES[name].read_text())
        for k, v in over.items():
            if k == "effects_add":  # effects listed on top of the scene's own
                d["effects"] = [*d.get("effects", []), *v]
            else:
                d[k] = {**d.get(k, {}), **v} if isinstance(v, dict) else v
        shutil.rmtree(out, ignore_errors=True)
        write_scene(scene_from_dict(d, SCENES[name].parent), out)
    return out


def scene_overrides(over: dict) -> dict:
    """The overrides of the rendered scene itself: ``over`` without the bench's photo options, "heldout_from" (the
    held-out photos of the scene with those overrides, :func:`run_synthetic`) and "photos_jpeg" (the photos saved as
    JPEGs of that quality, :func:`photos_folder`)."""
    return {k: v for k, v in over.items() if k not in ("heldout_from", "photos_jpeg")}


def config(preset: str | None, options: list[str] = ()):
    """configs/<preset>.yaml (the defaults for None) with ``options`` in the CLI's spelling on top, progress bars
    off: what ``python -m pipeline <stage> --config … <options>`` runs with."""
    from pipeline.config import config_from_args

    cfg = config_from_args(ROOT / "configs" / f"{preset}.yaml" if preset else None, options)
    cfg.train.progress = False
    return cfg


def stages(names: tuple[str, ...], ws: Path, cfg, **sources) -> None:
    """Run the named stages through the pipeline API (each skipped when up to date)."""
    from pipeline.stages import run_stage

    for name in names:
        run_stage(name, ws, cfg, **(sources if name == "cameras" else {}))


def textured(ws: Path):
    """The textured GLB of a workspace: trimesh mesh and its texture (float RGB)."""
    from pipeline.texture.export import read_textured

    return read_textured(ws / "mesh" / "textured.glb")


def dtu_heldout(n: int) -> list[int]:
    """The DTU views held out of training (every 7th of the ``n`` registered ones, sorted order)."""
    return [i for i in range(n) if i % 7 == 0]


def photos_folder(syn: Path, out: Path, jpeg_quality: int | None = None) -> Path:
    """A user's folder: the scene's training photos and its held-out photos (prefixed ``heldout_``; those of a
    scene with ``photo_scale`` > 1 at the photos' size); as the PNG renders, or with ``jpeg_quality`` as JPEGs of that
    quality (4:2:0 chroma, as cameras and phones save them)."""
    import cv2

    from synth.phone import save_jpeg

    out.mkdir(parents=True)
    photos = [(p, p.stem) for p in sorted((syn / "images").glob("*.png"))]
    held = syn / "gt" / "heldout" / ("photos" if (syn / "gt" / "heldout" / "photos").is_dir() else "images")
    photos += [(p, f"{HELDOUT}{p.stem}") for p in sorted(held.glob("*.png"))]
    for p, stem in photos:
        if jpeg_quality is None:
            shutil.copy2(p, out / f"{stem}.png")
        else:
            save_jpeg(cv2.imread(str(p), cv2.IMREAD_COLOR), out / f"{stem}.jpg", quality=jpeg_quality)
    return out


def mask_iou(ws: Path, gt_masks: dict[str, Path]) -> float:
    """Mean IoU of a workspace's masks against GT masks (by stem; undistortion may crop ≤ 1 px)."""
    ious = [view_mask_iou(ws / "masks" / f"{stem}.png", gp) for stem, gp in gt_masks.items()
            if (ws / "masks" / f"{stem}.png").exists()]
    return float(np.mean(ious)) if ious else float("nan")


def view_mask_iou(mask: Path, gt: Path) -> float:
    """IoU of one mask file against its GT mask (the GT cropped to the mask's size)."""
    import cv2

    a = cv2.imread(str(mask), 0) > 127
    b = cv2.imread(str(gt), 0) > 127
    b = b[: a.shape[0], : a.shape[1]]
    return float((a & b).sum() / max(1, (a | b).sum()))


def _render_at(tm, tex, K, R, centre, photo: np.ndarray):
    """The textured mesh rendered at a camera, at the photo's size: (image, hit mask)."""
    from pipeline.render.textured import render_textured

    h, w = photo.shape[:2]
    return render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, K, R, centre, w, h)


def render_psnr(tm, tex, K, R, centre, photo: np.ndarray, mask: np.ndarray, gain_fit: bool = False) -> float:
    """PSNR of the textured mesh at a camera against a photo, over ``mask`` ∪ the mesh's pixels; ``gain_fit``: as
    :func:`image_psnr` says."""
    img, hit = _render_at(tm, tex, K, R, centre, photo)
    return image_psnr(img, hit, photo, mask, gain_fit)


def render_psnrs(tm, tex, K, R, centre, photo: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """:func:`render_psnr` raw and with the photo's own colour gains fitted, from one render."""
    img, hit = _render_at(tm, tex, K, R, centre, photo)
    return image_psnr(img, hit, photo, mask), image_psnr(img, hit, photo, mask, gain_fit=True)


def reaimed_psnr(caster, K: np.ndarray, R: np.ndarray, centre: np.ndarray, photo: np.ndarray,
                 mask: np.ndarray) -> tuple[float, float]:
    """(PSNR, degrees turned): :func:`bench.reaim.reaim`'s render against ``photo`` over ``mask`` ∪ the mesh's pixels
    (as :func:`image_psnr`)."""
    from bench.reaim import degrees_turned, reaim

    Rd, img, hit = reaim(caster, K, R, centre, photo, mask)
    return image_psnr(img, hit, photo, mask), degrees_turned(Rd)


def reaimed_psnrs(tm, tex, views: list[tuple]) -> dict:
    """The held-out figure with each view re-aimed (:mod:`bench.reaim`): mean PSNR and mean degrees turned over
    ``views`` = (K, R, centre, photo path, mask path)."""
    from pipeline.render.textured import TexturedCaster

    caster = TexturedCaster(tm.vertices, tm.faces, tm.visual.uv, tex)
    out = [reaimed_psnr(caster, K, R, c, _read_rgb(p), _read_mask(m)) for K, R, c, p, m in views]
    return {"psnr_reaimed": float(np.mean([o[0] for o in out])) if out else float("nan"),
            "reaim_deg": float(np.mean([o[1] for o in out])) if out else float("nan")}


def image_psnr(img: np.ndarray, hit: np.ndarray, photo: np.ndarray, mask: np.ndarray, gain_fit: bool = False) -> float:
    """PSNR of a render ``img`` (H, W, 3) whose mesh covers ``hit`` against a photo, over ``mask`` ∪ ``hit``.
    ``gain_fit``: after scaling each colour channel of the render by :func:`photo_gains` there (a photo's own
    exposure and white balance cannot be predicted by one texture; what remains is the texture's error), clipped to
    [0, 1] as the camera clips (else a brighter view's clipped pixels count against the right texture)."""
    from dvr.metrics import masked_psnr

    m = mask | hit
    if gain_fit:
        img = np.clip(img * photo_gains(img, photo, m), 0.0, 1.0)
    return masked_psnr(img, photo, m)


def photo_gains(img: np.ndarray, photo: np.ndarray, where: np.ndarray) -> np.ndarray:
    """(3,) the least-squares gains per colour channel from a render ``img`` to a photo over the pixels ``where``
    the photo is not over-exposed (a clipped channel only says "at least this bright"); ones where none is left."""
    from pipeline.texture.config import TextureConfig

    fit = where & (photo < TextureConfig.clipped_level).all(-1)
    if not fit.any():
        return np.ones(3)
    a, b = img[fit], photo[fit]
    return (a * b).sum(0) / np.maximum((a * a).sum(0), 1e-12)


def _read_rgb(path: Path) -> np.ndarray:
    import cv2

    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB) / 255.0


def _read_mask(path: Path) -> np.ndarray:
    from dvr.data import read_mask

    return read_mask(path) > 0


PHOTO_STAGES = ("cameras", "masks", "depth")
"""The stages run on the whole photo folder before training (their outputs are shared by the rows that train)."""


def photo_stage_options(options: list[str]) -> list[str]:
    """The options of a knob that set the stages run on the whole photo folder before training (``--cameras.x v``,
    ``--masks.x v``, ``--depth.x v``), in the CLI's spelling."""
    out = []
    for i, o in enumerate(options):
        if o.startswith(tuple(f"--{stage}." for stage in PHOTO_STAGES)):
            out += [o] + ([options[i + 1]] if i + 1 < len(options) and not options[i + 1].startswith("--") else [])
    return out


def photo_stage_preset(preset: str | None) -> str | None:
    """``preset`` when configs/<preset>.yaml changes options of the :data:`PHOTO_STAGES`, else None: those stages are
    then the defaults' and shared between presets."""
    if not preset:
        return None
    cfg, default = config(preset), config(None)
    return preset if any(getattr(cfg, stage) != getattr(default, stage) for stage in PHOTO_STAGES) else None


def train_mesh_texture(ws: Path, preset: str, options: list[str]) -> None:
    """Stages train, mesh and texture with the preset and the knob's options."""
    stages(("train", "mesh", "texture"), ws, config(preset, options))


def true_cameras_of(gtc, hc) -> dict[str, tuple]:
    """Per photo name of a photos-only run (``000000``…, the held-out ``heldout_000000``…): its true cameras (the
    training ones ``gtc`` or the held-out ones ``hc``) and its index there."""
    return {**{f"{i:06d}": (gtc, i) for i in range(len(gtc))}, **{f"{HELDOUT}{i:06d}": (hc, i) for i in range(len(hc))}}


def true_in_sfm_frame(gtc, hc, names: list[str], est) -> tuple[np.ndarray, np.ndarray, tuple]:
    """A photos-only run's photos ``names`` (SfM's cameras ``est``, in the same order): their true camera centres
    and rotations (:func:`true_cameras_of` ``gtc``, ``hc``) and the similarity (s, R, t) from the true world into
    SfM's frame, fitted on the centres."""
    from dvr.metrics import umeyama

    gt_of = true_cameras_of(gtc, hc)
    centres = np.stack([gt_of[n][0].sfm_centers[gt_of[n][1]] for n in names])
    rotations = np.stack([gt_of[n][0].R[gt_of[n][1]] for n in names])
    return centres, rotations, umeyama(centres, est.sfm_centers)


def similarity_matrix(sim: tuple) -> np.ndarray:
    """(4, 4) homogeneous matrix of the similarity ``sim`` = (s, R, t): x ↦ s R x + t."""
    s, R, t = sim
    return np.block([[s * R, t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])


class HeldoutPsnrs(NamedTuple):
    """Per held-out photo of a photos-only run (:func:`heldout_psnrs`)."""
    at_sfm: list[float]  # at the poses SfM gave the photos it registered
    at_sfm_gain_fit: list[float]  # the same renders after fitting each photo's own colour gains (image_psnr)
    at_true: list[float]  # at every photo's true pose brought into SfM's frame


def heldout_psnrs(tm, tex, held: list[Path], masks: Path, names: list[str], est, hc, sim: tuple) -> HeldoutPsnrs:
    """PSNR of a photos-only run's textured mesh at its held-out photos ``held`` (their masks in ``masks``): at the
    poses SfM gave those it registered (``est``, names ``names``), raw and with the photo's own colour gains fitted
    (what the texture scores apart from the photo's exposure, which no model can know), and at every one's true pose
    (``hc``) brought into SfM's frame by ``sim`` = (s, R, t), with SfM's mean focal length."""
    s, R, t = sim
    out = HeldoutPsnrs([], [], [])
    for i, p in enumerate(held):
        photo, gm = _read_rgb(p), _read_mask(masks / p.name)
        if f"{HELDOUT}{p.stem}" in names:  # at the pose SfM gave the held-out photo: one render, both figures
            k = names.index(f"{HELDOUT}{p.stem}")
            raw, fitted = render_psnrs(tm, tex, est.K[k], est.R[k], est.sfm_centers[k], photo, gm)
            out.at_sfm.append(raw)
            out.at_sfm_gain_fit.append(fitted)
        out.at_true.append(render_psnr(tm, tex, est.K.mean(0), hc.R[i] @ R.T, s * R @ hc.sfm_centers[i] + t, photo,
                                       gm))
    return out


def run_synthetic(spec: dict, work: Path, knobs: dict) -> dict:
    """A synthetic scene end to end (GT cameras and masks, or photos only through SfM), measured."""
    import trimesh

    from dvr.cameras import load_cameras
    from dvr.metrics import chamfer_fscore, pose_errors
    from pipeline.workspace import Workspace

    cli_over, over = knobs.get(spec.get("knob"), ([], {}))
    syn = scene(spec["scene"], scene_overrides(over))
    # "heldout_from": measure against the held-out photos of the scene with these overrides (same cameras)
    ref = scene(spec["scene"], over["heldout_from"]) if "heldout_from" in over else syn
    gtc, hc = load_cameras(syn / "cameras.npz"), load_cameras(ref / "gt" / "heldout" / "cameras.npz")
    held = sorted((ref / "gt" / "heldout" / "images").glob("*.png"))
    extra: dict = {}
    if spec["cameras"] == "gt" and over.get("cameras", {}).get("photo_scale", 1) > 1:
        raise ValueError(f"{spec}: photos larger than the ground truth (photo_scale) only go through the cameras stage")
    if spec["cameras"] == "gt":
        ws = work / "ws"
        shutil.copytree(syn, ws, ignore=shutil.ignore_patterns("gt", "depth"))
        train_mesh_texture(ws, spec["preset"], cli_over)
        secs = Workspace(ws).seconds()
        s, R, t = 1.0, np.eye(3), np.zeros(3)
        tm, tex = textured(ws)
        both = [render_psnrs(tm, tex, hc.K[i], hc.R[i], hc.sfm_centers[i], _read_rgb(p),
                             _read_mask(ref / "gt" / "heldout" / "masks" / p.name)) for i, p in enumerate(held)]
        psnr = [raw for raw, _ in both]
        extra["psnr_gain_fit"] = float(np.mean([fitted for _, fitted in both]))
        extra.update(reaimed_psnrs(tm, tex, [(hc.K[i], hc.R[i], hc.sfm_centers[i], p,
                                              ref / "gt" / "heldout" / "masks" / p.name) for i, p in enumerate(held)]))
    else:
        full = work / "all"
        stages(("cameras", "masks", "depth"), full, config(spec["preset"], photo_stage_options(cli_over)),
               images=photos_folder(syn, work / "photos", over.get("photos_jpeg")))
        from dvr.data import list_images

        names = [p.stem for p in list_images(full / "images")]
        est = load_cameras(full / "cameras.npz")
        gt_c, gt_R, (s, R, t) = true_in_sfm_frame(gtc, hc, names, est)  # GT world → SfM frame
        extra["pose"] = pose_errors(est.sfm_centers, est.R, gt_c, gt_R)
        extra["registered"] = f"{len(names)}/{len(gtc) + len(hc)}"
        gt_masks = {**{f"{i:06d}": syn / "gt" / "masks" / f"{i:06d}.png" for i in range(len(gtc))},
                    **{f"{HELDOUT}{i:06d}": syn / "gt" / "heldout" / "masks" / f"{i:06d}.png" for i in range(len(hc))}}
        extra["mask_iou"] = mask_iou(full, gt_masks)
        extra["support"] = (Workspace(full).stamp("cameras") or {}).get("support")
        extra["rung"] = (Workspace(full).stamp("cameras") or {}).get("rung")
        ws = work / "ws"
        subset_workspace(full, ws, [k for k, n in enumerate(names) if not n.startswith(HELDOUT)])
        train_mesh_texture(ws, spec["preset"], cli_over)
        secs = {**Workspace(full).seconds(), **Workspace(ws).seconds()}
        tm, tex = textured(ws)
        psnrs = heldout_psnrs(tm, tex, held, syn / "gt" / "heldout" / "masks", names, est, hc, (s, R, t))
        psnr = psnrs.at_sfm
        extra["psnr_gt_pose"] = float(np.mean(psnrs.at_true))
        if psnrs.at_sfm_gain_fit:
            extra["psnr_gain_fit"] = float(np.mean(psnrs.at_sfm_gain_fit))
        at = {n: k for k, n in enumerate(names)}
        extra.update(reaimed_psnrs(tm, tex, [
            (est.K[k], est.R[k], est.sfm_centers[k], p, syn / "gt" / "heldout" / "masks" / p.name)
            for p in held if (k := at.get(f"{HELDOUT}{p.stem}")) is not None]))
        extra["heldout_registered"] = f"{len(psnr)}/{len(held)}"
    gt = trimesh.load(syn / "gt" / "mesh.ply")
    gt.apply_transform(similarity_matrix((s, R, t)))
    geo = chamfer_fscore(trimesh.load(ws / "mesh" / "clean.ply"), gt, n=50000)
    return {"seconds": secs, "chamfer_rel": geo["chamfer_rel"], "fscore": geo["fscore"],
            "psnr": float(np.mean(psnr)) if psnr else float("nan"), **extra}


def run_cameras(spec: dict, work: Path, conditions: dict) -> dict:
    """The cameras stage alone on a capture condition: rung, registered photos, pose error, seconds."""
    from dvr.cameras import load_cameras
    from dvr.data import list_images
    from dvr.metrics import pose_errors
    from pipeline.workspace import Workspace

    name, over, prepare = conditions[spec["condition"]]
    syn = scene(name, over)
    photos = prepare(syn, work / "photos") if prepare else syn / "images"
    ws = work / "ws"
    from pipeline.errors import StageError
    from pipeline.stages import run_stage

    try:
        run_stage("cameras", ws, images=photos)
        rc = 0
    except StageError as exc:  # the one-line error a user would see
        print(f"error: {exc}")
        rc = 2
    stamp = Workspace(ws).stamp("cameras") or {}
    gtc = load_cameras(syn / "cameras.npz")
    out = {"seconds": {"cameras": Workspace(ws).seconds().get("cameras", 0.0)}, "rung": stamp.get("rung"),
           "rungs": stamp.get("rungs"), "stopped": rc != 0, "support": stamp.get("support")}
    if rc != 0:
        out["registered"] = f"0/{len(gtc)}"
        return out
    est = load_cameras(ws / "cameras.npz")
    stems = [p.stem for p in list_images(ws / "images")]
    flags_file = photos.parent / "phone_flags.json"  # a phone folder: file names and EXIF rolls of the views
    if flags_file.exists():
        from synth.phone import upright_roll

        rec = json.loads(flags_file.read_text())
        idx = [int(rec[s]["source"]) for s in stems]
        gt_R = np.stack([upright_roll(gtc.R[i], rec[s]["flag"]) for i, s in zip(idx, stems)])
    else:
        idx = [int(s) for s in stems]
        gt_R = gtc.R[idx]
    out["registered"] = f"{len(idx)}/{len(gtc)}"
    out["pose"] = pose_errors(est.sfm_centers, est.R, gtc.sfm_centers[idx], gt_R)
    if (syn / "gt" / "board.json").exists() and (ws / "board.json").exists():
        out["metric"] = metric_error(est, gtc, idx, json.loads((syn / "gt" / "board.json").read_text()))
    return out


def metric_error(est, gtc, idx: list[int], gt_board: dict) -> dict:
    """A printed board put the cameras in metres in the board's frame: their centres against the true ones in that
    frame, without any alignment (mm), and the scale of the similarity between the two (1: metric scale exact)."""
    from dvr.cameras import transform_points
    from dvr.metrics import umeyama

    T = np.asarray(gt_board["world_to_board"])
    gt = transform_points(T, gtc.sfm_centers[idx])
    err = np.linalg.norm(est.sfm_centers - gt, axis=1)
    s, _, _ = umeyama(gt, est.sfm_centers)
    return {"centre_err_mm_mean": float(1000 * err.mean()), "centre_err_mm_max": float(1000 * err.max()),
            "scale": float(s)}


def run_dtu(spec: dict, work: Path, knobs: dict | None = None) -> dict:
    """DTU scan24 through our SfM (``spec["reference_cameras"]``: DTU's own cameras) and automatic masks (all 49
    photos), every 7th photo held out of training."""
    from bench.dtu_reference import dtu_reference
    from dvr.cameras import load_cameras
    from dvr.data import list_images
    from dvr.metrics import pose_errors
    from pipeline.workspace import Workspace

    options = (knobs or {}).get(spec.get("knob"), ([], {}))[0]
    cams_opts = photo_stage_options(options)  # a knob of those stages gets its own SfM run, else the shared one
    preset = photo_stage_preset(spec["preset"])  # so does a preset that sets them
    full = RUNS / ("dtu_all" + ("-" + "_".join(o.strip("-").replace(".", "_") for o in cams_opts) if cams_opts else "")
                   + (f"-preset_{preset}" if preset else "")
                   + ("-reference_cameras" if spec.get("reference_cameras") else ""))
    if not (full / ".stages" / "depth.json").exists():
        shutil.rmtree(full, ignore_errors=True)
        given = {}
        if spec.get("reference_cameras"):  # DTU's own calibration instead of SfM (features triangulated at it)
            from bench.dtu_reference import write_reference_cameras

            given = {"given_cameras": write_reference_cameras(DTU, RUNS / "dtu_reference" / "cameras.npz")}
        stages(("cameras", "masks", "depth"), full, config(preset, cams_opts), images=DTU / "images", **given)
    cams = load_cameras(full / "cameras.npz")
    paths = list_images(full / "images")
    names = [p.stem for p in paths]
    _, Rg, Cg, _ = dtu_reference(DTU)
    idx = [int(n) for n in names]  # registered photos (all 49 when SfM registers them all)
    pose = pose_errors(cams.sfm_centers, cams.R, Cg[idx], Rg[idx])
    held = dtu_heldout(len(names))
    ws = work / "ws"
    subset_workspace(full, ws, [i for i in range(len(names)) if i not in held])
    train_mesh_texture(ws, spec["preset"], options)
    scores = photo_scores(full, ws, paths, held)
    shared = Workspace(full).seconds()
    secs = {**shared, **{k: v for k, v in Workspace(ws).seconds().items() if k not in shared}}
    stamp = Workspace(full).stamp("cameras") or {}
    return {"seconds": secs, "chamfer_rel": None, "fscore": None, "pose": pose, **scores,
            "registered": f"{len(names)}/49", "support": stamp.get("support"), "rung": stamp.get("rung"),
            "views": {"train": len(names) - len(held), "heldout": len(held), "registered": len(names)}}


def photo_scores(full: Path, ws: Path, paths: list[Path], held: list[int], hand: Path | None = None) -> dict:
    """The textured mesh of ``ws`` (trained without the ``held`` views of ``full``, whose images are ``paths``) at
    every photo's pose: PSNR at the held-out photos (raw, on the mesh's pixels, with the photo's own colour gains
    fitted, re-aimed) and at the training photos, over the automatic mask ∪ the mesh's pixels; with ``hand`` (a
    folder of :func:`undistorted_hand_masks`) also ``psnr_hand``, at the held-out photos over the hand mask ∪ the
    mesh's pixels: the object's true outline, which does not grow or shrink with the automatic masks."""
    from dvr.cameras import load_cameras
    from dvr.metrics import masked_psnr
    from pipeline.render.textured import TexturedCaster, render_textured

    cams = load_cameras(full / "cameras.npz")
    tm, tex = textured(ws)
    caster = TexturedCaster(tm.vertices, tm.faces, tm.visual.uv, tex)
    psnr, psnr_hit, cover, psnr_train, fitted, fitted_train, reaimed, by_hand = [], [], [], [], [], [], [], []
    for i, path in enumerate(paths):
        photo = _read_rgb(path)
        h, w = photo.shape[:2]
        img, hit = render_textured(tm.vertices, tm.faces, tm.visual.uv, tex, cams.K[i], cams.R[i],
                                   cams.sfm_centers[i], w, h)
        mask = _read_mask(full / "masks" / f"{path.stem}.png")
        if i not in held:  # the textured mesh at the photos it was made from
            psnr_train.append(image_psnr(img, hit, photo, mask))
            fitted_train.append(image_psnr(img, hit, photo, mask, gain_fit=True))
            continue
        psnr.append(image_psnr(img, hit, photo, mask))
        reaimed.append(reaimed_psnr(caster, cams.K[i], cams.R[i], cams.sfm_centers[i], photo, mask))
        fitted.append(image_psnr(img, hit, photo, mask, gain_fit=True))
        psnr_hit.append(masked_psnr(img, photo, hit))
        cover.append(float((mask & hit).sum() / max(1, mask.sum())))
        if hand is not None:
            by_hand.append(image_psnr(img, hit, photo, hand_mask(hand, path.stem, (h, w))))
    hand_score = {"psnr_hand": float(np.mean(by_hand))} if by_hand else {}
    return {**hand_score, "psnr": float(np.mean(psnr)), "psnr_on_model": float(np.mean(psnr_hit)),
            "psnr_train": float(np.mean(psnr_train)), "psnr_gain_fit": float(np.mean(fitted)),
            "psnr_train_gain_fit": float(np.mean(fitted_train)), "mask_covered": float(np.mean(cover)),
            "psnr_reaimed": float(np.mean([r[0] for r in reaimed])),
            "reaim_deg": float(np.mean([r[1] for r in reaimed])), "psnr_per_view": [round(x, 2) for x in psnr]}


def heldout_scores(full: Path, ws: Path, preset: str, options: list[str], hand: Path | None = None) -> dict:
    """A real capture's workspace ``full`` (cameras, masks, depth of every photo) trained into ``ws`` without every
    7th photo (:func:`dtu_heldout`) with the preset and ``options``: :func:`photo_scores` at the photos held out (over
    the hand masks too, given their folder ``hand`` made by :func:`undistorted_hand_masks`), and ``views``, the
    split's counts."""
    from dvr.data import list_images

    paths = list_images(full / "images")
    held = dtu_heldout(len(paths))
    subset_workspace(full, ws, [i for i in range(len(paths)) if i not in held])
    train_mesh_texture(ws, preset, options)
    views = {"train": len(paths) - len(held), "heldout": len(held), "registered": len(paths)}
    return {**photo_scores(full, ws, paths, held, hand), "views": views}


def run_real(spec: dict, work: Path) -> dict:
    """A real capture of :data:`REAL` from its photos alone, as a user runs it (default options): cameras, masks and
    depth on every photo, training without every 7th registered photo, PSNR there; with hand masks, the automatic
    masks' IoU against them."""
    from pipeline.workspace import Workspace

    src, photos = capture_photos(spec["scene"])
    full = RUNS / f"real_{spec['scene']}"
    if not (full / ".stages" / "depth.json").exists():
        shutil.rmtree(full, ignore_errors=True)
        stages(("cameras", "masks", "depth"), full, config(None), images=photos)
    ws = work / "ws"
    hand = undistorted_hand_masks(full, src / "masks") if (src / "masks").is_dir() else None
    scores = heldout_scores(full, ws, spec["preset"], [], hand)
    shared = Workspace(full).seconds()
    secs = {**shared, **{k: v for k, v in Workspace(ws).seconds().items() if k not in shared}}
    stamp = Workspace(full).stamp("cameras") or {}
    n_photos = len([p for p in photos.iterdir() if p.is_file()])
    iou = masks_iou(full, hand) if hand is not None else None
    return {"seconds": secs, "chamfer_rel": None, "fscore": None, **scores, "mask_iou": iou,
            "registered": f"{scores['views']['registered']}/{n_photos}", "rung": stamp.get("rung"),
            "support": stamp.get("support")}


def capture_photos(scene: str) -> tuple[Path, Path]:
    """The folder of a real capture of :data:`REAL` or :data:`FOLDERS` (for a folder: the capture it comes from, whose
    hand masks it shares) and the folder of its photos (a folder's made once, under ``bench/runs``)."""
    if scene in REAL:
        return REAL[scene], REAL[scene] / "images"
    capture, take, long_side = FOLDERS[scene]
    photos = RUNS / f"photos_{scene}"
    if not photos.is_dir() or len(list(photos.iterdir())) != take:
        take_photos(REAL[capture] / "images", photos, take, long_side)
    return REAL[capture], photos


def take_photos(src: Path, out: Path, take: int, long_side: int = 0) -> Path:
    """``take`` photos of the folder ``src``, evenly spaced in name order, into ``out`` (made afresh), each resized to
    ``long_side`` (0: copied as is); ``bench/subset.py`` on the command line."""
    import cv2

    from pipeline.inputs.photos import list_photos, read_photo

    photos = list_photos(src)[0]
    if not 2 <= take <= len(photos):
        raise SystemExit(f"{src}: {len(photos)} photos; --take must be between 2 and that")
    out = fresh_folder(out)
    for i in np.linspace(0, len(photos) - 1, take).round().astype(int):
        photo = photos[i]
        if long_side <= 0:
            shutil.copy(photo, out / photo.name)
            continue
        img = read_photo(photo)
        scale = long_side / max(img.shape[:2])
        size = (round(img.shape[1] * scale), round(img.shape[0] * scale))
        cv2.imwrite(str(out / f"{photo.stem}.jpg"), cv2.resize(img, size, interpolation=cv2.INTER_CUBIC),
                    [cv2.IMWRITE_JPEG_QUALITY, 92])
    return out


def undistorted_hand_masks(full: Path, hand: Path) -> Path:
    """Hand masks of the original photos (``hand``, named like them) the way of a workspace's photos: to the size SfM
    saw, through COLMAP's undistortion of its model; the folder of the results (``<name>.png`` at the undistorted
    size, ``full/hand_masks_undistorted/images``)."""
    import cv2

    from pipeline.colmaplib import pycolmap

    model = full / "sfm" / "sparse" / "best"
    rec = pycolmap.Reconstruction(model)
    tmp = fresh_folder(full / "hand_masks")
    for i in rec.reg_image_ids():
        name = rec.image(i).name
        cam = rec.camera(rec.image(i).camera_id)
        m = cv2.imread(str(hand / f"{Path(name).stem}.png"), cv2.IMREAD_GRAYSCALE)
        m = cv2.resize(m, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(tmp / name), cv2.merge([m, m, m]))
    out = full / "hand_masks_undistorted"
    shutil.rmtree(out, ignore_errors=True)
    pycolmap.undistort_images(out, model, tmp, output_type="COLMAP")
    return out / "images"


def hand_mask(folder: Path, stem: str, shape: tuple[int, int]) -> np.ndarray:
    """The undistorted hand mask ``stem`` of :func:`undistorted_hand_masks`'s ``folder`` at ``shape`` (H, W), bool."""
    import cv2

    m = cv2.imread(str(folder / f"{stem}.png"), cv2.IMREAD_GRAYSCALE)
    return cv2.resize(m, (shape[1], shape[0]), interpolation=cv2.INTER_AREA) > 127


def masks_iou(full: Path, folder: Path) -> float:
    """Mean IoU of a workspace's automatic masks against the hand masks in ``folder`` (:func:`undistorted_hand_masks`),
    each at its mask's size."""
    import cv2

    ious = []
    for p in sorted((full / "masks").glob("*.png")):
        auto = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127
        m = hand_mask(folder, p.stem, auto.shape)
        ious.append(float((auto & m).sum() / max(1, (auto | m).sum())))
    return float(np.mean(ious))
