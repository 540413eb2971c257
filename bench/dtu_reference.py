"""Reference cameras of ../shared/data/dtu_scan24 for its 384x384 images (see its SOURCE.txt):
K from world_mat_i, cx -= 200, first two rows × 0.32; the scale_mat maps the unit sphere to DTU mm."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dvr.cameras import decompose_projection


def dtu_reference(folder: Path):
    """K (N,3,3), R (N,3,3), centres (N,3) in DTU mm, and scale_mat."""
    z = np.load(Path(folder) / "cameras.npz")
    n = len([k for k in z.files if k.startswith("world_mat_") and not k.startswith("world_mat_inv")])
    Ks, Rs, Cs = [], [], []
    for i in range(n):
        K, R, t = decompose_projection(z[f"world_mat_{i}"][:3, :4])
        K = K.copy()
        K[0, 2] -= 200.0
        K[:2] *= 0.32
        Ks.append(K), Rs.append(R), Cs.append(-R.T @ t)
    return np.stack(Ks), np.stack(Rs), np.stack(Cs), z["scale_mat_0"]


def write_reference_cameras(folder: Path, out: Path) -> Path:
    """DTU's cameras for its 384×384 photos as an IDR/NeuS ``cameras.npz`` (``world_mat_i`` = K [R | t] of the crop,
    ``scale_mat_i`` as given) at ``out``, for the cameras stage's ``--given-cameras``, whose resizing from the
    originals' size would not undo the crop."""
    Ks, Rs, Cs, scale = dtu_reference(folder)
    mats = {}
    for i, (K, R, C) in enumerate(zip(Ks, Rs, Cs)):
        world = np.eye(4)
        world[:3] = K @ np.hstack([R, (-R @ C)[:, None]])
        mats[f"world_mat_{i}"], mats[f"scale_mat_{i}"] = world, scale
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **mats)
    return out
