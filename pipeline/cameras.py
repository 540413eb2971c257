"""Stage ``cameras``: photos → ``sfm/`` (COLMAP database + sparse model), ``images/``, ``cameras.npz``, ``points.ply``.

SfM runs in-process with pycolmap: SIFT, matching chosen by image count, incremental (or global) mapping,
undistortion to PINHOLE. EXIF orientation: every photo is read with its EXIF orientation APPLIED
(OpenCV's default), and that upright copy is what SfM sees (``sfm/input/``) and what training sees
(``images/``) — COLMAP itself ignores the flag, so feeding it the originals would give it other pixels.
Inputs are never modified; everything is written inside the workspace.
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from dvr.cameras import decompose_projection, save_cameras, sphere_frame
from dvr.data import IMAGE_EXTS

from .cameras_config import CamerasConfig
from .config import config_hash
from .workspace import StageError, Workspace


# ----------------------------------------------------------------------------- inputs
def list_photos(folder: Path) -> tuple[list[Path], list[str]]:
    """Readable photos (sorted) and warnings about the files skipped."""
    if not folder.is_dir():
        raise StageError(f"{folder}: not a folder of photos; pass --images DIR")
    ok, skipped = [], []
    for p in sorted(folder.iterdir()):
        if not p.is_file():
            continue
        if p.suffix.lower() not in IMAGE_EXTS:
            skipped.append(f"{p.name} (not an image file)")
            continue
        if cv2.imread(str(p), cv2.IMREAD_REDUCED_GRAYSCALE_8) is None:
            skipped.append(f"{p.name} (unreadable)")
            continue
        ok.append(p)
    stems = [p.stem for p in ok]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise StageError(f"{folder}: several photos share the name(s) {', '.join(dup)} with different extensions; "
                         "rename them")
    return ok, skipped


def read_upright(path: Path, max_side: int) -> np.ndarray:
    """BGR image with EXIF orientation applied, downscaled (INTER_AREA) so its longest side ≤ max_side."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)  # applies EXIF orientation
    if img is None:
        raise StageError(f"{path}: unreadable image; remove it from the folder")
    h, w = img.shape[:2]
    s = min(1.0, max_side / max(h, w))
    if s < 1.0:
        img = cv2.resize(img, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    return img


def write_points(path: Path, pts: np.ndarray, cols: np.ndarray) -> None:
    """Binary PLY of coloured points (also valid when empty)."""
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
            "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    rec = np.zeros(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    if len(pts):
        rec["x"], rec["y"], rec["z"] = pts.T
        rec["r"], rec["g"], rec["b"] = cols.T
    path.write_bytes((head % len(pts)).encode() + rec.tobytes())


# ----------------------------------------------------------------------------- normalisation
def axes_convergence(centers: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Least-squares point closest to all optical axes."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, dirs):
        d = d / np.linalg.norm(d)
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ c
    return np.linalg.lstsq(A, b, rcond=None)[0]


def normalization(points: np.ndarray, Ps: np.ndarray, sizes: np.ndarray, centers: np.ndarray, dirs: np.ndarray,
                  margin: float, focals: np.ndarray | None = None) -> np.ndarray:
    """scale_mat (normalized → SfM) from sparse points seen inside most images, centred where the optical
    axes converge; the radius is a robust (97th percentile) extent of those points × margin, kept inside
    the cameras and, with ``focals``, inside what the images can show: at most 1.25 × the (median over views)
    sphere whose outline passes through the image corners. A weakly textured object in front of a textured
    background yields few points of its own (a white cow: 19 of 3900), and the background's would otherwise
    set the radius."""
    c = axes_convergence(centers, dirs)
    dist = np.linalg.norm(centers - c, axis=1)
    if len(points):
        ph = np.concatenate([points, np.ones((len(points), 1))], 1)
        x = np.einsum("nij,mj->nmi", Ps, ph)
        z = x[..., 2]
        uv = x[..., :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)[..., None]
        inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 1] >= 0) & (uv[..., 0] < sizes[:, None, 0]) & \
                 (uv[..., 1] < sizes[:, None, 1])
        central = inside.mean(0) >= 0.75
        pts = points[central] if central.sum() >= 20 else points
        r = np.percentile(np.linalg.norm(pts - c, axis=1), 97) * margin
    else:
        r = 0.5 * dist.min()
    if focals is not None:
        half_diag = np.arctan(0.5 * np.hypot(sizes[:, 0], sizes[:, 1]) / np.asarray(focals, float))
        r = min(r, 1.25 * float(np.median(dist * np.sin(half_diag))))
    return sphere_frame(c, min(r, 0.95 * dist.min()))


# ----------------------------------------------------------------------------- SfM
def _largest(recs: dict):
    if not recs:
        return None, None
    k = max(recs, key=lambda i: recs[i].num_reg_images())
    return k, recs[k]


def run_sfm(ws: Workspace, photos: list[Path], cfg: CamerasConfig):
    import pycolmap

    sfm = ws.root / "sfm"
    inp = sfm / "input"
    if sfm.exists():
        shutil.rmtree(sfm)
    inp.mkdir(parents=True)
    groups: dict[tuple[int, int], list[str]] = {}
    for p in photos:
        img = read_upright(p, cfg.max_side_sfm)
        cv2.imwrite(str(inp / f"{p.stem}.png"), img)
        groups.setdefault(img.shape[:2], []).append(f"{p.stem}.png")
    db = sfm / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    ext = pycolmap.FeatureExtractionOptions()
    ext.sift.max_num_features = cfg.max_features
    # one shared camera per image size (a phone's landscape and portrait shots are two cameras)
    for names in groups.values():
        pycolmap.extract_features(db, inp, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext)
    n = len(photos)
    if cfg.matching == "exhaustive" or (cfg.matching == "auto" and n <= 80):
        pycolmap.match_exhaustive(db)
    else:
        pycolmap.match_sequential(db)
    out = sfm / "sparse"
    out.mkdir()
    if cfg.mapper == "global":
        recs = pycolmap.global_mapping(db, inp, out)
    else:
        recs = pycolmap.incremental_mapping(db, inp, out)
    k, rec = _largest(recs)
    if rec is None or rec.num_reg_images() < 2:
        raise StageError(f"{inp}: SfM found no model (too few matches): photograph the object with more overlap "
                         "(≥ 60 % between neighbours), more texture, and sharp, well-lit images")
    rec, notes = prefer_pinhole(rec, cfg.pinhole_tolerance)
    for note in notes:
        print(f"cameras: {note}")
    best = out / "best"
    if best.exists():
        shutil.rmtree(best)
    best.mkdir()
    rec.write(best)
    return rec, best, inp


def prefer_pinhole(rec, tolerance: float):
    """Set the lens distortion to zero and re-adjust focal lengths and poses; keep that pinhole model when its
    mean reprojection error grows by at most ``tolerance`` (relative, +0.01 px); returns (model, notes).

    Object-centric captures hardly constrain distortion against focal length: on a synthetic pinhole scene
    COLMAP fitted k = 0.11 with the focal length 11 % long, and the pinhole re-fit recovered the true focal
    length to 0.01 % at the same reprojection error; undistorting by the spurious model cost ~13 dB held-out
    PSNR. A real lens keeps its distortion because a pinhole explains its tracks clearly worse.
    """
    import pycolmap

    if tolerance < 0:
        return rec, []
    trial = pycolmap.Reconstruction(rec)
    changed = []
    for cid, cam in trial.cameras.items():
        idx = list(cam.extra_params_idxs())
        if not idx or not np.any(cam.params[idx]):
            continue
        p = cam.params.copy()
        changed.append(f"camera {cid}: distortion {np.round(p[idx], 4).tolist()}, focal "
                       f"{np.round(p[list(cam.focal_length_idxs())], 1).tolist()}")
        p[idx] = 0.0
        cam.params = p
    if not changed:
        return rec, []
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_extra_params = False
    opts.print_summary = False
    pycolmap.bundle_adjustment(trial, opts)
    e0, e1 = rec.compute_mean_reprojection_error(), trial.compute_mean_reprojection_error()
    if e1 > (1 + tolerance) * e0 + 0.01:
        return rec, [f"lens distortion kept: as a pinhole the reprojection error grows from {e0:.3f} to {e1:.3f} px"]
    focal = [np.round(c.params[list(c.focal_length_idxs())], 1).tolist() for c in trial.cameras.values()]
    return trial, [f"{c} → pinhole" for c in changed] + [f"pinhole focal {focal}, mean reprojection error "
                                                         f"{e0:.3f} → {e1:.3f} px"]


def report_sfm(rec, names: list[str], cfg: CamerasConfig) -> dict:
    reg = {rec.image(i).name.rsplit(".", 1)[0] for i in rec.reg_image_ids()}
    missing = [n for n in names if n not in reg]
    info = {"registered": len(reg), "total": len(names), "mean_reprojection_error": rec.compute_mean_reprojection_error(),
            "mean_track_length": rec.compute_mean_track_length(), "points": rec.num_points3D(), "unregistered": missing}
    print(f"cameras: registered {len(reg)}/{len(names)}, mean reprojection error "
          f"{info['mean_reprojection_error']:.3f} px, mean track length {info['mean_track_length']:.2f}, "
          f"{info['points']} points")
    if missing:
        print(f"cameras: not registered: {', '.join(missing)}", file=sys.stderr)
    if len(reg) < max(3, cfg.min_registered_fraction * len(names)):
        raise StageError(f"only {len(reg)}/{len(names)} photos registered (missing: {', '.join(missing[:10])}"
                         f"{'...' if len(missing) > 10 else ''}); likely too little overlap or texture, or motion "
                         "blur — add photos between the missing ones")
    return info


def export_model(ws: Workspace, rec, image_dir: Path, cfg: CamerasConfig, names: list[str]) -> dict:
    """Undistort the model to PINHOLE, write images/, cameras.npz and points.ply."""
    import pycolmap

    und = ws.root / "sfm" / "undistorted"
    if und.exists():
        shutil.rmtree(und)
    model_dir = ws.root / "sfm" / "sparse" / "best"
    pycolmap.undistort_images(und, model_dir, image_dir, output_type="COLMAP")
    urec = pycolmap.Reconstruction(und / "sparse")
    by_name = {urec.image(i).name.rsplit(".", 1)[0]: urec.image(i) for i in urec.reg_image_ids()}
    if ws.images.exists():
        shutil.rmtree(ws.images)
    ws.images.mkdir(parents=True)
    Ks, Rs, ts, sizes, kept = [], [], [], [], []
    for name in names:
        if name not in by_name:
            continue
        im = by_name[name]
        cam = urec.camera(im.camera_id)
        img = cv2.imread(str(und / "images" / im.name), cv2.IMREAD_COLOR)
        h, w = img.shape[:2]
        s = min(1.0, cfg.max_side / max(h, w))
        nw, nh = round(w * s), round(h * s)
        if s < 1.0:
            img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(ws.images / f"{name}.png"), img)
        K = cam.calibration_matrix().copy()
        K[0] *= nw / w  # corner-origin pixel coordinates scale exactly
        K[1] *= nh / h
        pose = im.cam_from_world()
        M = pose.matrix() if callable(getattr(pose, "matrix", None)) else np.asarray(pose.matrix)
        Ks.append(K), Rs.append(M[:3, :3]), ts.append(M[:3, 3]), sizes.append((nw, nh)), kept.append(name)
    Ks, Rs, ts, sizes = np.stack(Ks), np.stack(Rs), np.stack(ts), np.asarray(sizes, float)
    pts, cols = [], []
    for pid, p in urec.points3D.items():
        if p.track.length() >= cfg.min_track_length:
            pts.append(p.xyz), cols.append(p.color)
    pts = np.asarray(pts).reshape(-1, 3)
    cols = np.asarray(cols, np.uint8).reshape(-1, 3)
    centers = -np.einsum("nji,nj->ni", Rs, ts)
    Ps = Ks @ np.concatenate([Rs, ts[:, :, None]], 2)
    S = normalization(pts, Ps, sizes, centers, Rs[:, 2, :], cfg.radius_margin, focals=Ks[:, 0, 0])
    save_cameras(ws.cameras, Ks, Rs, ts, S)
    write_points(ws.root / "points.ply", pts, cols)
    return {"views": kept, "radius": float(S[0, 0]), "center": S[:3, 3].tolist()}


# ----------------------------------------------------------------------------- given cameras
def import_cameras(ws: Workspace, photos: list[Path], cam_file: Path, cfg: CamerasConfig) -> dict:
    """Use given cameras (IDR/NeuS/DVR cameras.npz, one world_mat per photo in sorted order): skip SfM."""
    try:
        z = np.load(cam_file)
        n = len([k for k in z.files if k.startswith("world_mat_") and not k.startswith("world_mat_inv")])
    except Exception as exc:  # noqa: BLE001
        raise StageError(f"{cam_file}: cannot read cameras ({exc}); pass an IDR/DVR cameras.npz") from exc
    if n != len(photos):
        raise StageError(f"{cam_file}: {n} cameras for {len(photos)} photos; give one world_mat_i per photo")
    scale = z["scale_mat"] if "scale_mat" in z.files else z["scale_mat_0"] if "scale_mat_0" in z.files else np.eye(4)
    if ws.images.exists():
        shutil.rmtree(ws.images)
    ws.images.mkdir(parents=True)
    Ks, Rs, ts = [], [], []
    for i, p in enumerate(photos):
        full = cv2.imread(str(p), cv2.IMREAD_COLOR)
        h, w = full.shape[:2]
        img = read_upright(p, cfg.max_side)
        nh, nw = img.shape[:2]
        cv2.imwrite(str(ws.images / f"{p.stem}.png"), img)
        K, R, t = decompose_projection(np.asarray(z[f"world_mat_{i}"], float)[:3, :4])
        K = K.copy()
        K[0] *= nw / w
        K[1] *= nh / h
        Ks.append(K), Rs.append(R), ts.append(t)
    save_cameras(ws.cameras, np.stack(Ks), np.stack(Rs), np.stack(ts), np.asarray(scale, float))
    write_points(ws.root / "points.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    return {"views": [p.stem for p in photos], "given": str(cam_file)}


def import_colmap_model(ws: Workspace, photos: list[Path], images: Path, model: Path, cfg: CamerasConfig) -> dict:
    """Use a given COLMAP sparse model (cameras/images/points3D .bin or .txt, image names relative to the photo
    folder): skip SfM, undistort and normalise as after our own SfM."""
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(model)
    except Exception as exc:  # noqa: BLE001
        raise StageError(f"{model}: not a COLMAP sparse model ({exc}); pass the folder holding cameras.bin, "
                         "images.bin and points3D.bin (or their .txt)") from exc
    missing = [rec.image(i).name for i in rec.reg_image_ids() if not (images / rec.image(i).name).exists()]
    if rec.num_reg_images() == 0 or missing:
        raise StageError(f"{model}: {len(missing) or 'no'} registered image(s) of the model not found in {images} "
                         f"({', '.join(missing[:5])}); pass the photo folder the model was made from")
    best = ws.root / "sfm" / "sparse" / "best"
    best.mkdir(parents=True, exist_ok=True)
    rec.write(best)
    names = [p.stem for p in photos]
    info = report_sfm(rec, names, cfg)
    info.update(export_model(ws, rec, images, cfg, names))
    info["given"] = str(model)
    return info


def run(ws: Workspace, images: Path | None, cfg: CamerasConfig, cameras: Path | None = None,
        force: bool = False) -> bool:
    if images is None:
        raise StageError(f"{ws.root}: the cameras stage needs --images DIR (the photos)")
    images = Path(images).resolve()
    if ws.root == images or images in ws.root.parents:
        raise StageError(f"{ws.root}: the workspace must not be the photo folder or inside it; choose another OUT")
    h = config_hash({"cfg": cfg.__dict__, "images": str(images), "cameras": str(cameras)})
    outs = [ws.images, ws.cameras, ws.root / "points.ply"]
    ins = [images] + ([Path(cameras)] if cameras else [])
    if not force and ws.up_to_date("cameras", h, ins, outs):
        print(f"cameras: up to date ({ws.cameras})")
        return False
    ws.clear("cameras")
    ws.root.mkdir(parents=True, exist_ok=True)
    photos, skipped = list_photos(images)
    for s in skipped:
        print(f"warning: skipping {images / s.split(' (')[0]}: {s.split(' (', 1)[1][:-1]}", file=sys.stderr)
    if len(photos) < 3:
        raise StageError(f"{images}: {len(photos)} usable photo(s); at least 3 are needed (20–60 around the object is "
                         "typical)")
    t0 = time.perf_counter()
    if cameras is not None and Path(cameras).is_dir():
        info = import_colmap_model(ws, photos, images, Path(cameras), cfg)
    elif cameras is not None:
        info = import_cameras(ws, photos, Path(cameras), cfg)
    else:
        rec, _, inp = run_sfm(ws, photos, cfg)
        info = report_sfm(rec, [p.stem for p in photos], cfg)
        info.update(export_model(ws, rec, inp, cfg, [p.stem for p in photos]))
    ws.mark_done("cameras", h, time.perf_counter() - t0, {k: v for k, v in info.items() if k != "views"})
    print(f"cameras: {len(info['views'])} views → {ws.cameras}")
    return True
