"""A printed ChArUco board under the object: metric scale, the ground plane, and a textured mat for SfM.

When the photos show the board (``python -m pipeline board board.png`` prints one: 5 × 7 squares of 35 mm, ArUco
markers of the 4×4 dictionary), its corners are detected in every photo (OpenCV's ``CharucoDetector``), each
corner seen in at least two views is triangulated with the SfM cameras, and a similarity maps those points onto
the board's known corners. The cameras stage then moves the whole SfM frame into the board's (metres, origin at
the board's centre, z up, x along its rows of squares): ``cameras.npz``, ``points.ply`` and the SfM model, so the
mesh and the textured mesh come out in metres, and the board's plane is the support plane (z = 0). What was
found is written to ``board.json`` beside ``cameras.npz``. No board in the photos: nothing changes.

Pixel convention: OpenCV puts pixel centres on integers, this project at (j + 0.5, i + 0.5) (see the README), so
detected corners are shifted by half a pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dvr.atomic import write_json
from dvr.metrics import umeyama
from pipeline.errors import StageError
from pipeline.scene.support import SupportPlane, object_height, object_points

A4_MM = (210.0, 297.0)
"""Paper the printable page is laid out on (portrait, mm)."""
MIN_CORNERS = 6
"""Triangulated board corners needed for a fit (a similarity has 7 degrees of freedom; 6 points spread over a
plane pin it with room to spare)."""


@dataclass
class BoardSpec:
    """The printed board: squares (columns, rows), side of a square and of a marker (metres), ArUco dictionary."""

    squares: tuple[int, int] = (5, 7)
    square_m: float = 0.035
    marker_m: float = 0.026
    dictionary: str = "DICT_4X4_50"

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the board's grid of squares in metres."""
        return self.squares[0] * self.square_m, self.squares[1] * self.square_m

    def describe(self) -> str:
        """The board in words (messages, ``board.json``)."""
        return (f"{self.squares[0]}×{self.squares[1]} ChArUco, {1000 * self.square_m:g} mm squares, "
                f"{1000 * self.marker_m:g} mm markers, {self.dictionary}")

    def info(self) -> dict:
        """The board as ``board.json`` records it."""
        return {"board": self.describe(), "squares": list(self.squares), "square_m": self.square_m,
                "marker_m": self.marker_m, "dictionary": self.dictionary}


def board_spec(squares, square_mm: float, marker_mm: float, dictionary: str, where: str = "board") -> BoardSpec:
    """A validated :class:`BoardSpec` from sizes in mm; impossible sizes raise a one-line StageError naming
    ``where`` (the config fields or the command) and the fix."""
    sq = tuple(int(v) for v in squares)
    if len(sq) != 2 or min(sq) < 2:
        raise StageError(f"{where}: board squares {list(squares)} — give two counts ≥ 2 (columns rows), e.g. 5 7")
    if not (square_mm > 0 and 0 < marker_mm < square_mm):
        raise StageError(f"{where}: board marker {marker_mm:g} mm / square {square_mm:g} mm — the marker must be "
                         "smaller than the square (e.g. 26 and 35 mm)")
    if not hasattr(cv2.aruco, dictionary) or not dictionary.startswith("DICT_"):
        raise StageError(f"{where}: unknown ArUco dictionary '{dictionary}' — use e.g. DICT_4X4_50 or DICT_5X5_100")
    n_markers = sq[0] * sq[1] // 2
    available = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    if n_markers > available:
        raise StageError(f"{where}: a {sq[0]}×{sq[1]} board needs {n_markers} markers and {dictionary} has "
                         f"{available} — use a larger dictionary (e.g. DICT_4X4_250) or fewer squares")
    return BoardSpec(sq, square_mm / 1000.0, marker_mm / 1000.0, dictionary)


def spec_from_config(cfg) -> BoardSpec:
    """The board of a CamerasConfig (fields ``board_*``)."""
    return board_spec(cfg.board_squares, cfg.board_square_mm, cfg.board_marker_mm, cfg.board_dictionary,
                      "--cameras.board-squares/-square-mm/-marker-mm/-dictionary")


def make_board(spec: BoardSpec):
    """The OpenCV ``CharucoBoard`` of ``spec`` (generator and detector use this one definition)."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    return cv2.aruco.CharucoBoard(spec.squares, spec.square_m, spec.marker_m, d)


def board_texture(spec: BoardSpec, px_per_square: int) -> np.ndarray:
    """The board alone, (rows·px, columns·px) uint8, white paper 255, black ink 0; pixel (i, j) covers
    [j, j+1) × [i, i+1) / px squares of the board frame (x right, y down)."""
    w, h = spec.squares[0] * px_per_square, spec.squares[1] * px_per_square
    return make_board(spec).generateImage((w, h), marginSize=0, borderBits=1)


def page_image(spec: BoardSpec, dpi: int = 300, paper_mm: tuple[float, float] = A4_MM) -> np.ndarray:
    """A printable page (uint8, white paper) with the board centred at its true size at ``dpi``, and a caption
    that says what the board is and how long a square must measure."""
    px_mm = dpi / 25.4
    W, H = round(paper_mm[0] * px_mm), round(paper_mm[1] * px_mm)
    bw, bh = (round(s * 1000 * px_mm) for s in spec.size_m)
    if bw > W - 2 * 10 * px_mm or bh > H - 2 * 15 * px_mm:
        raise StageError(f"board: a {spec.size_m[0] * 1000:g} × {spec.size_m[1] * 1000:g} mm board does not fit a "
                         f"{paper_mm[0]:g} × {paper_mm[1]:g} mm page with margins — use fewer or smaller squares")
    page = np.full((H, W), 255, np.uint8)
    x0, y0 = (W - bw) // 2, (H - bh) // 2
    page[y0:y0 + bh, x0:x0 + bw] = make_board(spec).generateImage((bw, bh), marginSize=0, borderBits=1)
    text = f"{spec.describe()} - print at 100 % (no fit to page); a square must measure {1000 * spec.square_m:g} mm"
    thick = max(1, round(px_mm / 4))
    width = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 1.0, thick)[0][0]
    cv2.putText(page, text, (round(10 * px_mm), H - round(8 * px_mm)), cv2.FONT_HERSHEY_SIMPLEX,
                (W - 20 * px_mm) / width, 0, thick, cv2.LINE_AA)
    return page


def write_page(path: Path, spec: BoardSpec, dpi: int = 300) -> Path:
    """Write the printable page as a PNG that records its dpi (so printers print it at its true size)."""
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise StageError(f"{path}: the board is written as a PNG; give a name ending in .png")
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(page_image(spec, dpi)).save(path, dpi=(dpi, dpi))
    return path


# ----------------------------------------------------------------------------- detection and fit
def detect(image: np.ndarray, board) -> tuple[np.ndarray, np.ndarray]:
    """ChArUco corner ids (M,) and pixel positions (M, 2) (this project's convention: centres at +0.5) in an image
    (grey or BGR); empty arrays when the board is not seen."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    params = cv2.aruco.CharucoParameters()
    params.minMarkers = 1  # a corner next to one decoded marker (small photos decode few; the fit drops outliers)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board, params).detectBoard(grey)
    if ids is None or len(ids) == 0:
        return np.zeros(0, int), np.zeros((0, 2))
    return ids.ravel().astype(int), corners.reshape(-1, 2).astype(float) + 0.5


def triangulate(P: list[np.ndarray], uv: list[np.ndarray]) -> tuple[np.ndarray, float]:
    """Linear (DLT) triangulation of one point from its pixels ``uv`` in views with projections ``P`` (3 × 4);
    returns the point and its largest reprojection error (px)."""
    A = np.concatenate([np.stack([u[0] * p[2] - p[0], u[1] * p[2] - p[1]]) for p, u in zip(P, uv)])
    A /= np.linalg.norm(A[:, :3], axis=1, keepdims=True)
    X = np.linalg.svd(A)[2][-1]
    X = X[:3] / X[3] if abs(X[3]) > 1e-12 else np.full(3, np.inf)
    err = max(float(np.linalg.norm((p @ np.append(X, 1))[:2] / (p @ np.append(X, 1))[2] - u)) for p, u in zip(P, uv))
    return X, err


def board_points(spec: BoardSpec, ids: np.ndarray) -> np.ndarray:
    """Corners ``ids`` in the output frame: metres, origin at the board's centre, x along its rows, z up (towards
    the side the markers are printed on; OpenCV's board frame has y down and z into the board)."""
    obj = np.asarray(make_board(spec).getChessboardCorners(), float)[ids]
    w, h = spec.size_m
    return np.stack([obj[:, 0] - w / 2, h / 2 - obj[:, 1], -obj[:, 2]], 1)


class BoardMismatch(StageError):
    """The board is seen in many views but the cameras cannot triangulate its corners: the cameras are wrong."""


@dataclass
class BoardFit:
    """The board found in a capture: SfM → board frame similarity x_m = scale · R x + t, and what it rests on."""

    spec: BoardSpec
    scale: float
    """Metres per SfM unit."""
    R: np.ndarray
    t: np.ndarray
    views: int
    corners: int
    residual_mm: float
    """RMS distance of the triangulated corners from the printed ones after the fit (mm)."""

    @property
    def matrix(self) -> np.ndarray:
        """4×4 similarity SfM frame → board frame (metres): x ↦ scale · R x + t."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.scale * self.R, self.t
        return T

    def info(self, n_views: int) -> dict:
        """What ``board.json`` records of the fit (``n_views``: the photos searched)."""
        return {**self.spec.info(), "views": self.views, "of_views": n_views, "corners": self.corners,
                "metres_per_sfm_unit": self.scale, "residual_mm": round(self.residual_mm, 3),
                "sfm_to_metric": self.matrix.tolist(), "units": "metres",
                "frame": "board: origin at its centre, z up, x along its rows of squares"}


def _observations(images, Ps, board) -> tuple[dict[int, list], int]:
    """Per corner id the (P, uv) of the views that see it, and how many views saw the board."""
    obs: dict[int, list] = {}
    seen = 0
    for img, P in zip(images, Ps):
        ids, uv = detect(img, board)
        seen += len(ids) >= 4
        for k, x in zip(ids, uv) if len(ids) >= 4 else ():
            obs.setdefault(int(k), []).append((P, x))
    return obs, seen


def locate(images: list[np.ndarray], Ps: list[np.ndarray], spec: BoardSpec, max_error_px: float = 2.0
           ) -> BoardFit | None:
    """Find the board in ``images`` (views with projections ``Ps``, any frame and scale) and fit the similarity
    onto the printed board; None when fewer than ``MIN_CORNERS`` corners triangulate consistently."""
    obs, seen = _observations(images, Ps, make_board(spec))
    ids, X, errs = [], [], []
    for k, o in sorted(obs.items()):
        if len(o) >= 2:
            x, err = triangulate([p for p, _ in o], [u for _, u in o])
            errs.append(err)
            if err <= max_error_px * max(1.0, np.sqrt(len(o) / 2)) and np.isfinite(x).all():
                ids.append(k), X.append(x)
    if len(errs) >= MIN_CORNERS and np.median(errs) > 10 * max_error_px:  # not a misread corner: wrong cameras
        raise BoardMismatch(f"the printed board's corners, seen in {seen} views, do not meet where the SfM cameras "
                            f"put them ({len(errs) - len(ids)}/{len(errs)} corners off by a median "
                            f"{np.median(errs):.0f} px): the SfM poses are wrong")
    if len(ids) < MIN_CORNERS:
        return None
    ids, X = np.asarray(ids), np.asarray(X)
    Y = board_points(spec, ids)
    keep = np.ones(len(ids), bool)
    for _ in range(3):  # drop corners far off the fit (a marker misread), refit
        s, R, t = umeyama(X[keep], Y[keep])
        res = np.linalg.norm(s * X @ R.T + t - Y, axis=1)
        keep = res <= max(3 * np.median(res), 0.1 * spec.square_m)
        if keep.sum() < MIN_CORNERS:
            return None
    s, R, t = umeyama(X[keep], Y[keep])
    rms = float(np.sqrt(np.mean(np.linalg.norm(s * X[keep] @ R.T + t - Y[keep], axis=1) ** 2)))
    return BoardFit(spec, s, R, t, seen, int(keep.sum()), 1000 * rms)


# ----------------------------------------------------------------------------- use in the cameras stage
def to_board_frame(fit: BoardFit, Rs: np.ndarray, ts: np.ndarray, pts: np.ndarray):
    """Cameras (world → camera R, t) and points of the SfM frame expressed in the board's (metres): the same
    pixels, every length × ``fit.scale``."""
    Rn = Rs @ fit.R.T
    tn = fit.scale * ts - np.einsum("nij,j->ni", Rn, fit.t)
    return Rn, tn, fit.scale * pts @ fit.R.T + fit.t


def transform_model(fit: BoardFit, model_dir: Path) -> None:
    """Move a COLMAP model on disk into the board's frame (later stages read its points beside cameras.npz)."""
    from pipeline.colmaplib import pycolmap, write_model

    rec = pycolmap.Reconstruction(model_dir)
    rec.transform(pycolmap.Sim3d(fit.scale, pycolmap.Rotation3d(fit.R), fit.t))
    write_model(rec, model_dir)  # replaced whole: a kill leaves the model in one frame, never half of each


def board_support(pts: np.ndarray, centers: np.ndarray, target: np.ndarray, tolerance: float = 0.01,
                  min_cameras_above: float = 0.9) -> SupportPlane | None:
    """The board's plane z = 0 (board frame) as the support plane, when the cameras look down on it (a board
    propped up behind the object is no floor); heights and tolerance as in
    :func:`pipeline.scene.support.find_support`."""
    if np.mean(centers[:, 2] > 0) < min_cameras_above or target[2] <= 0:
        return None
    scale = float(np.median(np.linalg.norm(centers - target, axis=1)))
    tol = tolerance * scale
    up = np.array([0.0, 0, 1])
    height = object_height(object_points(pts, up, 0.0, target, scale, tol), up, 0.0, target)
    return SupportPlane(up, 0.0, int((np.abs(pts[:, 2]) < tol).sum()), tol, height, kind="board")


def _read_views(folder: Path, files: list[str], Ks: np.ndarray, sizes: np.ndarray):
    """The photos SfM saw (``folder/<file>``, full resolution: COLMAP's undistorter keeps each image's name, ours
    ``<stem>.png``, a given model's its own) and their intrinsics (``Ks`` are for the training size ``sizes``)."""
    images, K_full = [], []
    for file, K, (w, h) in zip(files, Ks, sizes):
        img = cv2.imread(str(folder / file), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise StageError(f"{folder / file}: unreadable; rerun the cameras stage with --force")
        images.append(img)
        K_full.append(np.diag([img.shape[1] / w, img.shape[0] / h, 1.0]) @ K)
    return images, np.stack(K_full)


def use_board(root: Path, undistorted: Path, files: list[str], Ks, Rs, ts, sizes, pts, cfg):
    """The cameras stage's hook: find the board in the undistorted photos (``files``: their names in
    ``undistorted/images``); when found, move cameras, points and the undistorted model into its frame (metres) and
    write ``board.json``. Returns (R, t, points, fit or None)."""
    (root / "board.json").unlink(missing_ok=True)
    if not cfg.board:
        return Rs, ts, pts, None
    spec = spec_from_config(cfg)
    images, K_full = _read_views(undistorted / "images", files, Ks, sizes)
    try:
        fit = locate(images, [K @ np.concatenate([R, t[:, None]], 1) for K, R, t in zip(K_full, Rs, ts)], spec)
    except BoardMismatch as exc:
        raise StageError(f"{undistorted.parent.parent}: {exc} — a symmetric or repetitive object that SfM matched "
                         "to the wrong side; add texture around it (a textured mat beside the board)") from exc
    if fit is None:
        return Rs, ts, pts, None
    Rs, ts, pts = to_board_frame(fit, Rs, ts, pts)
    transform_model(fit, undistorted / "sparse")
    write_json(root / "board.json", fit.info(len(files)), indent=1)
    print(f"cameras: board: {spec.describe()} seen in {fit.views}/{len(files)} views, {fit.corners} corners, "
          f"{fit.scale:.4g} m per SfM unit (corners fit to {fit.residual_mm:.2f} mm) → cameras, points and mesh in "
          "metres, origin at the board's centre, z up")
    return Rs, ts, pts, fit


