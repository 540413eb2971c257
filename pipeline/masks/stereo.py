"""Object/background evidence from multi-view stereo, for the automatic masks.

Colour models fail where the object has the backdrop's colours (dark hooves on a dark-speckled backdrop, a plate
printed like the wall behind it). Depth does not: an object pixel is photo-consistent with the neighbouring views
at some depth inside the object's unit sphere, a backdrop pixel at some depth beyond it.

For every view a plane sweep in inverse depth runs from the unit sphere's nearest point to the farthest
background point SfM saw; each hypothesis is scored by the colour difference (5×5 box-filtered L1) with its
``n_neighbors`` nearest views, keeping the mean of the best half (a point hidden in one neighbour must not count
against it). ``c_in`` is the best score among hypotheses inside the sphere, ``c_out`` among those beyond it.
Where one is clearly lower the pixel is labelled; textureless pixels (both low) and pixels seen by no neighbour
stay undecided for GrabCut.

With a support plane (the floor or table the object stands on, ``cams.ground``) hypotheses on it (within
``GROUND_BAND``) count for neither side, those below it for the background, and every ray that reaches the plane
is also scored at exactly the plane's depth as a background hypothesis: the floor around the object, its
texture and the shadows on it, are photo-consistent there.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from dvr.cameras import Cameras, pixel_centers, pixel_rays, project, sphere_bounds
from dvr.data import pad_stack
from pipeline.scene.support import GROUND_BAND

UNDECIDED, OBJECT, BACKGROUND = 0, 1, 2
BACKGROUND_RADIUS = 1.2
"""Radius of the normalized frame beyond which a point is background (the unit sphere is fitted to the object,
which may touch it; masks also take sparse points beyond it as background seeds)."""


def neighbours(centers: np.ndarray, k: int) -> np.ndarray:
    """Indices (N, k) of each camera's ``k`` nearest other cameras (by the angle seen from the sphere centre)."""
    u = centers / np.linalg.norm(centers, axis=1, keepdims=True).clip(1e-12)
    cos = u @ u.T
    np.fill_diagonal(cos, -np.inf)
    return np.argsort(-cos, axis=1)[:, : min(k, len(centers) - 1)]


@torch.no_grad()
def stereo_costs(images: torch.Tensor, cams: Cameras, far: np.ndarray, n_depths: int = 48, n_neighbors: int = 4,
                 patch: int = 5, outside: float = BACKGROUND_RADIUS,
                 sizes: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Best matching cost inside (``c_in``) and beyond (``c_out``) the unit sphere for every pixel, (N, H, W) each
    (inf where no hypothesis of that kind could be scored).

    Args:
        images: (N, H, W, 3) float in [0, 1], in the views' order of ``cams`` (normalized frame); views of other
            sizes padded to the canvas (top-left), their own (width, height) in ``sizes`` (N, 2).
        far: (N,) farthest ray depth to sweep to per view (e.g. the 95th percentile of its background points).
        outside: hypotheses count as background beyond this radius (the unit sphere is fitted to the object, which
            may touch it: a band between the two is neither).
    """
    N, H, W, _ = images.shape
    if len(cams) != N or far.shape != (N,):
        raise ValueError(f"{N} images, {len(cams)} cameras and {far.shape} far depths must agree")
    if N < 2:
        raise ValueError("stereo needs at least 2 views")
    dev = images.device
    imgs = images.permute(0, 3, 1, 2).contiguous()  # (N, 3, H, W)
    nb = neighbours(cams.centers, n_neighbors)
    K, R, t, P = (torch.from_numpy(a).to(dev, torch.float32) for a in (cams.K, cams.R, cams.t, cams.P))
    uv_ref = pixel_centers(H, W, device=dev).reshape(-1, 2)
    c_in = torch.full((N, H, W), float("inf"), device=dev)
    c_out = torch.full((N, H, W), float("inf"), device=dev)
    ground = None if cams.ground is None else torch.as_tensor(cams.ground, dtype=torch.float32, device=dev)
    for i in range(N):
        o, d = pixel_rays(K[i], R[i], t[i], uv_ref)
        near_s, far_s, hit = sphere_bounds(o, d)
        z_near = float(near_s[hit].min()) if hit.any() else 0.05
        z_far = max(float(far[i]), float(far_s.max()) * 1.05)
        inv = torch.linspace(1.0 / max(z_near, 1e-3), 1.0 / z_far, n_depths, device=dev)
        scorer = _Scorer(imgs, P, nb[i], i, patch, sizes)
        for z in 1.0 / inv:
            X = o + z * d  # (HW, 3)
            best = scorer(X)
            r = X.norm(dim=-1).view(H, W)
            inside, beyond = r < 1.0, r > outside
            if ground is not None:  # on the support: neither; below it: background
                hgt = (X @ ground[:3] + ground[3]).view(H, W)
                inside, beyond = inside & (hgt > GROUND_BAND), beyond | (hgt < -GROUND_BAND)
            c_in[i] = torch.where(inside, torch.minimum(c_in[i], best), c_in[i])
            c_out[i] = torch.where(beyond, torch.minimum(c_out[i], best), c_out[i])
        if ground is not None:  # the exact depth of the support plane along each ray: background evidence
            rate = d @ ground[:3]
            z_plane = torch.where(rate < -1e-9, -(o @ ground[:3] + ground[3]) / rate.clamp(max=-1e-9),
                                  torch.zeros_like(rate))
            best = scorer(o + z_plane[:, None] * d).view(H, W)
            on_plane = (z_plane > 0).view(H, W)
            c_out[i] = torch.where(on_plane, torch.minimum(c_out[i], best), c_out[i])
    return c_in, c_out


class _Scorer:
    """Matching cost of reference view ``i`` at 3-D points (one per pixel): 5×5 box-filtered L1 colour difference
    with each neighbour view, the mean of the best half (inf where fewer than half the neighbours see the point).
    All neighbours are warped and filtered in one batch."""

    def __init__(self, imgs: torch.Tensor, P: torch.Tensor, neighbours: np.ndarray, i: int, patch: int,
                 sizes: np.ndarray | None = None):
        _, _, H, W = imgs.shape
        sizes = np.tile([W, H], (len(imgs), 1)) if sizes is None else np.asarray(sizes)
        idx = torch.as_tensor(np.asarray(neighbours), dtype=torch.long, device=imgs.device)
        self.P, self.ref, self.patch = P[idx], imgs[i], patch
        self.nb_imgs = imgs[idx]  # (k, 3, H, W)
        wh = torch.as_tensor(sizes[np.asarray(neighbours)], dtype=torch.float32, device=imgs.device)
        self.w_k, self.h_k = wh[:, :1], wh[:, 1:]  # (k, 1) each neighbour's own width and height
        self.window = box_sums(torch.ones(1, 1, H, W, device=imgs.device), patch)[0, 0]  # pixels in each window

    def __call__(self, X: torch.Tensor) -> torch.Tensor:
        k, _, H, W = self.nb_imgs.shape
        uv, z = project(X, self.P)  # (k, HW, 2), (k, HW) in every neighbour
        grid = torch.stack([uv[..., 0] / W * 2 - 1, uv[..., 1] / H * 2 - 1], -1).view(k, H, W, 2)
        warped = F.grid_sample(self.nb_imgs, grid, align_corners=False, padding_mode="zeros")
        seen = (uv[..., 0] >= 0) & (uv[..., 0] <= self.w_k) & (uv[..., 1] >= 0) & (uv[..., 1] <= self.h_k) & (z > 1e-6)
        ok = seen.view(k, 1, H, W).float()
        diff = (warped - self.ref).abs().mean(1, keepdim=True)
        sums = box_sums(torch.cat([diff * ok, ok], 1), self.patch)
        num, den = sums[:, 0], sums[:, 1]  # the window's difference over its seen pixels, and how many are seen
        costs = torch.where(den > 0.99 * self.window, num / den.clamp_min(1e-6), torch.full_like(num, float("inf")))
        cs = costs.sort(dim=0).values
        return cs[: max(1, k // 2)].mean(0)


def box_sums(x: torch.Tensor, p: int) -> torch.Tensor:
    """Sums of ``x`` (B, C, H, W) over the ``p``×``p`` window (``p`` odd) centred on each pixel, clipped at the image
    borders, from a summed-area table in float64 (exact to float32 rounding; less than half ``avg_pool2d``'s time on
    a CPU)."""
    if p % 2 != 1:
        raise ValueError(f"window side {p} must be odd")
    r = p // 2
    table = F.pad(x.double(), (r + 1, r, r + 1, r)).cumsum(2).cumsum(3)
    return (table[..., p:, p:] - table[..., :-p, p:] - table[..., p:, :-p] + table[..., :-p, :-p]).to(x.dtype)


def stereo_labels(c_in: torch.Tensor, c_out: torch.Tensor, ratio: float = 0.5, min_cost: float = 0.03,
                  erode_px: int = 2) -> np.ndarray:
    """OBJECT where c_in < ratio·c_out and c_out > min_cost (the background hypothesis really fails),
    BACKGROUND where c_out < ratio·c_in and c_in > min_cost, else UNDECIDED; (N, H, W) uint8. Each label is
    eroded by ``erode_px`` (the matching window straddles silhouettes; specks are not evidence)."""
    both = torch.isfinite(c_in) & torch.isfinite(c_out)  # a side no neighbour could score proves nothing
    obj = (both & (c_in < ratio * c_out) & (c_out > min_cost)).cpu().numpy().astype(np.uint8)
    bg = (both & (c_out < ratio * c_in) & (c_in > min_cost)).cpu().numpy().astype(np.uint8)
    lab = np.full(obj.shape, UNDECIDED, np.uint8)
    k = np.ones((2 * erode_px + 1,) * 2, np.uint8)
    for i in range(len(lab)):
        lab[i][cv2.erode(obj[i], k) > 0] = OBJECT
        lab[i][cv2.erode(bg[i], k) > 0] = BACKGROUND
    return lab


def stereo_seed_labels(images: list[np.ndarray], cams: Cameras, far: np.ndarray, scale: float = 0.5,
                       n_depths: int = 32, ratio: float = 0.5, device: str | torch.device = "cpu",
                       outside: float = BACKGROUND_RADIUS) -> np.ndarray:
    """:func:`stereo_labels` of BGR uint8 ``images`` (each its own size) computed at ``scale`` × their size and
    brought back to it (nearest): one (H, W) uint8 array per image."""
    small, K = [], cams.K.copy()
    for v, im in enumerate(images):
        H, W = im.shape[:2]
        h, w = max(8, round(H * scale)), max(8, round(W * scale))
        small.append(cv2.resize(cv2.cvtColor(im, cv2.COLOR_BGR2RGB), (w, h), interpolation=cv2.INTER_AREA))
        K[v, 0] *= w / W
        K[v, 1] *= h / H
    canvas, sizes = pad_stack(small)
    c_in, c_out = stereo_costs(torch.from_numpy(canvas.astype(np.float32) / 255.0).to(device), replace(cams, K=K),
                               far, n_depths=n_depths, outside=outside, sizes=sizes)
    lab = stereo_labels(c_in, c_out, ratio, erode_px=1)
    return [cv2.resize(lab[v, :h, :w], (im.shape[1], im.shape[0]), interpolation=cv2.INTER_NEAREST)
            for v, ((w, h), im) in enumerate(zip(sizes, images))]
