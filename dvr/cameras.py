"""Cameras and rays.

Convention (docs/design.md, Conventions): ``cameras.npz`` holds per view ``world_mat_i`` = K·[R|t] (world → pixels, SfM
frame) and one ``scale_mat`` mapping the normalized frame (object inside the unit sphere) to the SfM frame.
Pixel (row i, column j) has its centre at continuous coordinates (j + 0.5, i + 0.5): the COLMAP convention,
and the one ``grid_sample(..., align_corners=False)`` uses, so colours looked up at projected points agree
with the pixels rays are shot through. Ray depth is the Euclidean distance along a unit direction from the
camera centre, in the normalized frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from kornia.geometry import create_meshgrid
from kornia.geometry.conversions import convert_points_to_homogeneous

from dvr.atomic import save_npz


@dataclass
class Cameras:
    """Pinhole cameras in the normalized frame (all arrays float64 numpy)."""

    K: np.ndarray  # (N, 3, 3) intrinsics
    R: np.ndarray  # (N, 3, 3) world(normalized) → camera rotation
    t: np.ndarray  # (N, 3) translation
    scale_mat: np.ndarray  # (4, 4) normalized → SfM frame
    ground: np.ndarray | None = None  # (4,) support plane n·x + d = 0 in this frame (unit n up), or None

    def __len__(self) -> int:
        return len(self.K)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres in the normalized frame, (N, 3)."""
        return -np.einsum("nji,nj->ni", self.R, self.t)

    @property
    def P(self) -> np.ndarray:
        """Projection matrices normalized frame → pixels, (N, 3, 4)."""
        Rt = np.concatenate([self.R, self.t[:, :, None]], axis=2)
        return self.K @ Rt

    @property
    def sfm_centers(self) -> np.ndarray:
        """Camera centres in the SfM frame (that of ``cameras.npz``), (N, 3)."""
        return to_sfm(self.centers, self.scale_mat)

    def subset(self, idx) -> "Cameras":
        """The cameras ``idx`` (indices, a slice or a mask), same frame and support plane."""
        return Cameras(self.K[idx], self.R[idx], self.t[idx], self.scale_mat, self.ground)

    def reframe(self, center: np.ndarray, radius: float) -> "Cameras":
        """The same cameras in a frame whose unit sphere is the sphere (``center``, ``radius``) of this frame:
        x_this = center + radius · x_new. ``scale_mat`` becomes new → SfM; depths scale by 1/radius."""
        if not (radius > 0 and np.isfinite(radius)):
            raise ValueError(f"reframe: radius must be positive and finite, got {radius}")
        t = (np.einsum("nij,j->ni", self.R, np.asarray(center, float)) + self.t) / radius
        to_this = sphere_frame(center, radius)
        return Cameras(self.K.copy(), self.R.copy(), t, self.scale_mat @ to_this, plane_in_frame(self.ground, to_this))


def plane_in_frame(plane: np.ndarray | None, T: np.ndarray) -> np.ndarray | None:
    """Plane (4,) n·x + d = 0 of frame A as a plane of frame B, where x_A = T x_B (4×4 similarity); unit normal."""
    if plane is None:
        return None
    q = np.asarray(plane, float) @ T
    return q / np.linalg.norm(q[:3])


def plane_height(plane: np.ndarray, points):
    """Signed height above a plane (4,) with unit normal of points (..., 3), numpy or torch."""
    return points[..., 0] * float(plane[0]) + points[..., 1] * float(plane[1]) + points[..., 2] * float(plane[2]) \
        + float(plane[3])


def in_contact_band(height, band: float):
    """True where a height above the support plane (:func:`plane_height`; numpy or torch) lies in the contact band
    ``0 ≤ h < band``, where the object meets its support."""
    return (height >= 0) & (height < band)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (..., 3) mapped by a 4×4 affine map ``T``: ``points @ T[:3, :3].T + T[:3, 3]``."""
    return points @ T[:3, :3].T + T[:3, 3]


def to_sfm(points: np.ndarray, scale_mat: np.ndarray) -> np.ndarray:
    """Normalized-frame points (..., 3) in the SfM frame: ``x @ S[:3, :3].T + S[:3, 3]`` (``scale_mat`` S: normalized →
    SfM)."""
    return transform_points(scale_mat, points)


def to_normalized(points: np.ndarray, scale_mat: np.ndarray, uniform: bool = False) -> np.ndarray:
    """SfM-frame points (..., 3) in the normalized frame: ``(x − S[:3, 3]) @ inv(S[:3, :3]).T``. ``uniform``: divide by
    ``S[0, 0]`` instead, for a ``scale_mat`` without rotation (a sphere's, :func:`sphere_frame`); the two differ in the
    last bits."""
    if uniform:
        return (points - scale_mat[:3, 3]) / scale_mat[0, 0]
    return (points - scale_mat[:3, 3]) @ np.linalg.inv(scale_mat[:3, :3]).T


def project_points(P: np.ndarray, points: np.ndarray, blas: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """numpy :func:`project`: points (M, 3) through a projection P (3, 4) or projections (N, 3, 4): pixel coordinates
    (M, 2) or (N, M, 2) and depths z (M,) or (N, M); a |z| below 1e-12 divides as 1e-12 (test z > 0 for the points
    in front). ``blas=False``: the products summed by numpy's einsum loop instead of BLAS (the last bits differ: a
    point on an image border may fall on the other side)."""
    ph = np.concatenate([points, np.ones((len(points), 1))], 1)
    x = ph @ np.swapaxes(P, -1, -2) if blas else np.einsum("...ij,mj->...mi", P, ph)
    z = x[..., 2]
    return x[..., :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)[..., None], z


def sphere_frame(center: np.ndarray, radius: float) -> np.ndarray:
    """4×4 map x ↦ center + radius · x from the frame whose unit sphere is the sphere (``center``, ``radius``)."""
    T = np.eye(4)
    T[:3, :3] *= radius
    T[:3, 3] = center
    return T


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split a 3×4 projection P = s·K[R|t] into K (K[2,2]=1, positive focal lengths), R (det +1) and t."""
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    if not np.all(np.isfinite(P)):
        raise ValueError("projection matrix contains NaN or Inf")
    M = P[:, :3]
    if abs(np.linalg.det(M)) < 1e-300:
        raise ValueError("projection matrix is singular (rank < 3)")
    # RQ decomposition via QR of the flipped transpose.
    flip = np.eye(3)[::-1]
    q, r = np.linalg.qr((flip @ M).T)
    K = flip @ r.T @ flip
    R = flip @ q.T
    # make the diagonal of K positive
    sgn = np.sign(np.diag(K))
    sgn[sgn == 0] = 1
    S = np.diag(sgn)
    K, R = K @ S, S @ R
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:  # projective sign: P and -P are the same camera
        R, t = -R, -t
    K = K / K[2, 2]
    return K, R, t


def _camera_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of the npz at ``path`` as float64 (ValueError naming the file: unreadable, corrupt, not numbers)."""
    try:
        with np.load(path) as data:
            raw = {k: data[k] for k in data.files}  # members are read (and CRC-checked) here, not later
    except Exception as exc:  # noqa: BLE001 - zipfile, pickle and OS errors alike: the file is not a camera file
        raise ValueError(f"{path}: cannot read camera file ({type(exc).__name__}); rerun the cameras stage "
                         "(--force) or give an npz with world_mat_i") from exc
    arrays = {}
    for k, a in raw.items():
        try:
            arrays[k] = np.asarray(a, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {k} holds {a.dtype} values, not numbers; write K·[R|t] per view as "
                             "world_mat_0, world_mat_1, ...") from exc
    return arrays


def load_cameras(path: str | Path, n_views: int | None = None) -> Cameras:
    """Read an IDR/DVR/NeuS-style ``cameras.npz`` (``world_mat_i`` and ``scale_mat`` or ``scale_mat_i``)."""
    path = Path(path)
    data = _camera_arrays(path)
    keys = [k for k in data if k.startswith("world_mat_") and not k.startswith("world_mat_inv")]
    if not keys:
        raise ValueError(f"{path}: no world_mat_i entries; write K·[R|t] per view as world_mat_0, world_mat_1, ...")
    odd = [k for k in keys if not k.rsplit("_", 1)[1].isdigit()]
    if odd:
        raise ValueError(f"{path}: {odd[0]} is no camera index; name the views world_mat_0, world_mat_1, ...")
    idx = sorted(int(k.rsplit("_", 1)[1]) for k in keys)
    if idx != list(range(len(idx))):
        raise ValueError(f"{path}: world_mat indices must be 0..N-1 without gaps, got {idx[:5]}...")
    if n_views is not None and len(idx) != n_views:
        raise ValueError(f"{path}: holds {len(idx)} cameras but the workspace has {n_views} images")
    scale = data.get("scale_mat", data.get("scale_mat_0", np.eye(4)))
    if scale.shape != (4, 4) or not np.isfinite(scale).all() or abs(np.linalg.det(scale)) < 1e-300:
        raise ValueError(f"{path}: scale_mat must be a finite, invertible 4x4 matrix (normalized → world), got shape "
                         f"{scale.shape}")
    ground = data.get("ground_plane")
    if ground is not None and (ground.size != 4 or not np.isfinite(ground).all()):
        raise ValueError(f"{path}: ground_plane must be 4 finite numbers (a, b, c, d of ax + by + cz + d = 0)")
    ground = plane_in_frame(ground.reshape(4), scale) if ground is not None else None
    Ks, Rs, ts = [], [], []
    for i in idx:
        W = data[f"world_mat_{i}"]
        if W.shape not in ((3, 4), (4, 4)):
            raise ValueError(f"{path}: world_mat_{i} has shape {W.shape}, expected 3x4 or 4x4")
        try:
            K, R, t = decompose_projection(W[:3, :4] @ scale)
        except ValueError as exc:
            raise ValueError(f"{path}: world_mat_{i}: {exc}; give K·[R|t] of that view") from exc
        Ks.append(K), Rs.append(R), ts.append(t)
    return Cameras(np.stack(Ks), np.stack(Rs), np.stack(ts), scale, ground)


def save_cameras(path: str | Path, K: np.ndarray, R: np.ndarray, t: np.ndarray, scale_mat: np.ndarray,
                 ground: np.ndarray | None = None) -> None:
    """Write ``cameras.npz``: K, R, t given in the SfM frame; ``scale_mat`` maps normalized → SfM; ``ground``: the
    support plane (4,) n·x + d = 0 in the SfM frame (n up), stored as ``ground_plane`` when the object rests on one."""
    out = {"scale_mat": scale_mat}
    if ground is not None:
        out["ground_plane"] = np.asarray(ground, float)
    for i in range(len(K)):
        W = np.eye(4)
        W[:3, :4] = K[i] @ np.concatenate([R[i], t[i][:, None]], axis=1)
        out[f"world_mat_{i}"] = W
        out[f"scale_mat_{i}"] = scale_mat
        out[f"camera_mat_{i}"] = K[i]
    save_npz(Path(path), **out)  # whole or absent (dvr.atomic)


def pixel_rays(
    K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, uv: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through continuous pixel coordinates ``uv`` (..., 2) of one camera.

    Returns origins and unit directions (..., 3) in the camera's world (normalized) frame.
    Pass ``uv = (j + 0.5, i + 0.5)`` for the centre of pixel (i, j).
    """
    if uv.shape[-1] != 2:
        raise ValueError(f"uv must end in 2, got {tuple(uv.shape)}")
    pix = torch.cat([uv, torch.ones_like(uv[..., :1])], dim=-1)  # not kornia's: that one refuses a single uv (2,)
    d_cam = pix @ torch.linalg.inv(K).T
    d_world = d_cam @ R  # R^T d for row vectors
    d_world = d_world / d_world.norm(dim=-1, keepdim=True)
    center = -(R.T @ t)
    return center.expand_as(d_world), d_world


def pixel_centers(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(height, width, 2) continuous coordinates (j + 0.5, i + 0.5) of every pixel centre (kornia's pixel grid)."""
    return create_meshgrid(height, width, normalized_coordinates=False, device=device, dtype=dtype)[0] + 0.5


def image_rays(cams: Cameras, height: int, width: int, device=None, dtype=torch.float32):
    """Rays for every pixel centre of every view: origins, dirs of shape (N, H, W, 3)."""
    uv = pixel_centers(height, width, dtype=torch.float64)
    os, ds = [], []
    for i in range(len(cams)):
        o, d = pixel_rays(torch.from_numpy(cams.K[i]), torch.from_numpy(cams.R[i]), torch.from_numpy(cams.t[i]), uv)
        os.append(o), ds.append(d)
    return torch.stack(os).to(device=device, dtype=dtype), torch.stack(ds).to(device=device, dtype=dtype)


def sphere_bounds(origins: torch.Tensor, dirs: torch.Tensor, radius: float = 1.0):
    """Entry and exit depths of rays with the sphere |p| = radius, and whether they cross it.

    Rays from inside the sphere start at depth 0. Missing rays get near = far = 0 (finite) and
    ``valid = False``; no NaN is produced (the discriminant is clamped before the square root).
    """
    b = (origins * dirs).sum(-1)
    c = (origins * origins).sum(-1) - radius * radius
    disc = b * b - c
    valid = disc > 0
    s = torch.sqrt(disc.clamp_min(0.0))
    near = (-b - s).clamp_min(0.0)
    far = -b + s
    valid = valid & (far > 0)
    near = torch.where(valid, near, torch.zeros_like(near))
    far = torch.where(valid, far, torch.zeros_like(far))
    return near, far, valid


def project(points: torch.Tensor, P: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project points (M, 3) with projections P (N, 3, 4): pixel coords (N, M, 2) and depth z (N, M)."""
    x = torch.einsum("nij,mj->nmi", P, convert_points_to_homogeneous(points))
    z = x[..., 2]
    zs = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
    return x[..., :2] / zs[..., None], z
