"""Training data: a workspace's images, masks, cameras and optional sparse depth, and the ray sampler.

Layout (docs/design.md, "Workspace"): ``images/`` (view i = i-th file in sorted order), ``masks/`` (same stems, PNG),
``depth/`` (same stems, npz with ``uv`` (K, 2) continuous pixel coordinates, ``depth`` (K,) ray depth in
the normalized frame, ``confidence`` (K,)), ``cameras.npz``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from kornia.geometry.conversions import convert_points_to_homogeneous

from dvr.cameras import Cameras, load_cameras, sphere_frame

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}


def list_images(folder: Path) -> list[Path]:
    """The image files of ``folder`` (by extension), sorted: view i is the i-th."""
    return sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file())


def read_rgb(path: Path) -> np.ndarray:
    """Read an image as float32 RGB in [0, 1], (H, W, 3)."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: not a readable image; replace or remove it")
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img.astype(np.float32) / 255.0


def read_mask(path: Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a mask as float32 {0, 1} (grey > 127), (H, W); ``shape``: the (H, W) it must have (its image's)."""
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise ValueError(f"{path}: not a readable mask image; write a PNG with 0 = background, 255 = object")
    if shape is not None and m.shape != shape:
        raise ValueError(f"{path}: mask is {m.shape[1]}x{m.shape[0]} but its image is {shape[1]}x{shape[0]}; "
                         "resize the mask to the image")
    return (m > 127).astype(np.float32)


def pad_stack(arrays: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Stack images of different sizes on a common canvas (top-left aligned, zero padding): (N, H, W, ...) and the
    views' own (width, height), (N, 2). Pixel coordinates of a view are the same on the canvas."""
    H = max(a.shape[0] for a in arrays)
    W = max(a.shape[1] for a in arrays)
    out = np.zeros((len(arrays), H, W, *arrays[0].shape[2:]), arrays[0].dtype)
    for k, a in enumerate(arrays):
        out[k, : a.shape[0], : a.shape[1]] = a
    return out, np.array([(a.shape[1], a.shape[0]) for a in arrays], np.int64)


@dataclass
class SceneData:
    """All views of a workspace on one device. Views may differ in size (a phone's portrait and landscape
    photos): images and masks are padded to a common canvas and ``sizes`` holds each view's own (width, height)."""

    images: torch.Tensor  # (N, H, W, 3), padded
    masks: torch.Tensor  # (N, H, W) in {0, 1}, padded with 0
    cams: Cameras
    Kinv: torch.Tensor  # (N, 3, 3)
    Rt: torch.Tensor  # (N, 3, 3) camera → world rotation (R^T)
    centers: torch.Tensor  # (N, 3)
    P: torch.Tensor  # (N, 3, 4) normalized → pixels
    names: list[str]
    depth_views: torch.Tensor | None = None  # (K,) view of each sparse depth
    depth_uv: torch.Tensor | None = None  # (K, 2)
    depth_val: torch.Tensor | None = None  # (K,)
    to_normalized: np.ndarray | None = None  # 4×4 map of this frame to the normalized frame of cameras.npz
    sizes: torch.Tensor | None = None  # (N, 2) long: each view's (width, height); None: all fill the canvas

    def __post_init__(self):
        if self.sizes is None:
            N, H, W = self.masks.shape
            self.sizes = torch.tensor([[W, H]] * N, dtype=torch.long, device=self.masks.device)

    @property
    def frame(self) -> np.ndarray:
        """4×4 map from this data's frame to the normalized frame of ``cameras.npz`` (identity unless reframed)."""
        return np.eye(4) if self.to_normalized is None else self.to_normalized

    def reframe(self, center: np.ndarray, radius: float) -> "SceneData":
        """The same views in the frame whose unit sphere is (``center``, ``radius``) of the current one
        (see :meth:`dvr.cameras.Cameras.reframe`): cameras, projections and sparse depths change, pixels do not."""
        cams = self.cams.reframe(center, radius)
        dev = self.masks.device
        f32 = dict(device=dev, dtype=torch.float32)
        return SceneData(
            images=self.images, masks=self.masks, cams=cams, Kinv=self.Kinv, Rt=self.Rt,
            centers=torch.from_numpy(cams.centers).to(**f32), P=torch.from_numpy(cams.P).to(**f32), names=self.names,
            depth_views=self.depth_views, depth_uv=self.depth_uv,
            depth_val=None if self.depth_val is None else self.depth_val / radius,
            to_normalized=self.frame @ sphere_frame(center, radius), sizes=self.sizes,
        )

    @property
    def shape(self) -> tuple[int, int, int]:
        """(views, canvas height, canvas width)."""
        return tuple(self.masks.shape)  # type: ignore[return-value]

    def view_size(self, view: int) -> tuple[int, int]:
        """(width, height) of one view."""
        w, h = self.sizes[view].tolist()
        return int(w), int(h)

    def rays(self, view: torch.Tensor, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays (origins, unit dirs) through continuous pixel coordinates uv (B, 2) of views (B,)."""
        d = torch.einsum("bij,bj->bi", self.Kinv[view], convert_points_to_homogeneous(uv))
        d = torch.einsum("bij,bj->bi", self.Rt[view], d)
        d = d / d.norm(dim=-1, keepdim=True)
        return self.centers[view], d


def load_scene(ws: Path, device: torch.device, use_depth: bool = True, views: list[int] | None = None) -> SceneData:
    """Load images/, masks/, cameras.npz (and depth/ when present and ``use_depth``) of workspace ``ws``."""
    ws = Path(ws)
    img_dir, mask_dir = ws / "images", ws / "masks"
    if not img_dir.is_dir():
        raise FileNotFoundError(f"{img_dir}: missing; run the cameras stage (or synth) first")
    paths = list_images(img_dir)
    if not paths:
        raise FileNotFoundError(f"{img_dir}: no images; run the cameras stage first")
    cams = load_cameras(ws / "cameras.npz", n_views=len(paths))
    if views is not None:
        paths = [paths[i] for i in views]
        cams = cams.subset(views)
    imgs, masks = [], []
    for p in paths:
        img = read_rgb(p)
        mp = mask_dir / f"{p.stem}.png"
        if not mp.exists():
            raise FileNotFoundError(f"{mp}: missing mask for {p.name}; run the masks stage")
        imgs.append(img)
        masks.append(read_mask(mp, img.shape[:2]))
    f32 = dict(device=device, dtype=torch.float32)
    K = torch.from_numpy(cams.K)
    R = torch.from_numpy(cams.R)
    images, sizes = pad_stack(imgs)
    data = SceneData(
        images=torch.from_numpy(images).to(**f32),
        masks=torch.from_numpy(pad_stack(masks)[0]).to(**f32),
        sizes=torch.from_numpy(sizes).to(device),
        cams=cams,
        Kinv=torch.linalg.inv(K).to(**f32),
        Rt=R.transpose(1, 2).contiguous().to(**f32),
        centers=torch.from_numpy(cams.centers).to(**f32),
        P=torch.from_numpy(cams.P).to(**f32),
        names=[p.stem for p in paths],
    )
    depth_dir = ws / "depth"
    if use_depth and depth_dir.is_dir():
        dv, duv, dd = [], [], []
        for i, p in enumerate(paths):
            f = depth_dir / f"{p.stem}.npz"
            if not f.exists():
                continue
            try:
                with np.load(f) as z:
                    uv = np.asarray(z["uv"], np.float32).reshape(-1, 2)
                    d = np.asarray(z["depth"], np.float32).reshape(-1)
            except Exception as exc:  # noqa: BLE001 - a truncated npz (zipfile, EOF), a missing key, not numbers
                raise ValueError(f"{f}: unreadable sparse depth ({type(exc).__name__}); rerun the depth stage "
                                 "(depth --force)") from exc
            if len(uv) != len(d):
                raise ValueError(f"{f}: {len(uv)} pixels for {len(d)} depths; rerun the depth stage (depth --force)")
            ok = np.isfinite(d) & (d > 0) & np.isfinite(uv).all(1)
            # a sparse depth is object evidence only where the mask agrees (table points inside the sphere)
            h, w = masks[i].shape
            pixel = np.nan_to_num(np.floor(uv), nan=0.0, posinf=w, neginf=0.0)  # cast to int without numpy's warning
            ij = np.clip(pixel, 0, [w - 1, h - 1]).astype(int)
            ok &= masks[i][ij[:, 1], ij[:, 0]] > 0.5
            dv.append(np.full(ok.sum(), i)), duv.append(uv[ok]), dd.append(d[ok])
        if dv and sum(len(x) for x in dv) > 0:
            data.depth_views = torch.from_numpy(np.concatenate(dv)).to(device=device, dtype=torch.long)
            data.depth_uv = torch.from_numpy(np.concatenate(duv)).to(**f32)
            data.depth_val = torch.from_numpy(np.concatenate(dd)).to(**f32)
    return data


class RaySampler:
    """Uniform pixel sampling (every pixel of every view equally likely, whatever the views' sizes) plus
    oversampling of a band around mask boundaries."""

    def __init__(self, data: SceneData, boundary_fraction: float = 0.25, band_px: int | None = None,
                 generator: torch.Generator | None = None):
        self.data = data
        N, H, W = data.shape
        self.boundary_fraction = boundary_fraction
        self.gen = generator
        sizes = data.sizes.cpu()
        self.widths = sizes[:, 0]
        counts = sizes[:, 0] * sizes[:, 1]
        self.starts = torch.cumsum(counts, 0) - counts  # first flat index of each view among the valid pixels
        self.n_pix = int(counts.sum())
        band_px = band_px or max(2, round(0.02 * max(H, W)))
        k = np.ones((2 * band_px + 1, 2 * band_px + 1), np.uint8)
        band = []
        for m, (w, h) in zip(data.masks.cpu().numpy().astype(np.uint8), sizes.tolist()):
            b = np.zeros_like(m, bool)
            own = m[:h, :w]
            b[:h, :w] = cv2.dilate(own, k) != cv2.erode(own, k)
            band.append(b)
        idx = np.flatnonzero(np.stack(band))
        self.band = torch.from_numpy(idx).to(data.masks.device)

    def uniform(self, n: int) -> torch.Tensor:
        """``n`` flat canvas indices (into (N, H, W)) of pixels drawn uniformly from the views' own pixels."""
        _, H, W = self.data.shape
        u = torch.randint(0, self.n_pix, (n,), generator=self.gen, device="cpu")
        view = torch.searchsorted(self.starts, u, right=True) - 1
        rem = u - self.starts[view]
        w = self.widths[view]
        return (view * (H * W) + (rem // w) * W + rem % w).to(self.data.masks.device)

    def sample(self, n: int):
        """:meth:`pixels` of ``n`` pixels: ``boundary_fraction`` of them from the mask-boundary band, the rest
        :meth:`uniform`."""
        dev = self.data.masks.device
        nb = int(round(n * self.boundary_fraction)) if self.band.numel() > 0 else 0
        u = self.uniform(n - nb)
        if nb:
            b = self.band[torch.randint(0, self.band.numel(), (nb,), generator=self.gen, device="cpu").to(dev)]
            u = torch.cat([u, b])
        return self.pixels(u)

    def pixels(self, flat: torch.Tensor):
        """Rays, colours, mask values and view indices of flat pixel indices into (N, H, W)."""
        N, H, W = self.data.shape
        view = flat // (H * W)
        rem = flat % (H * W)
        i, j = rem // W, rem % W
        uv = torch.stack([j, i], dim=-1).to(torch.float32) + 0.5
        o, d = self.data.rays(view, uv)
        return o, d, self.data.images[view, i, j], self.data.masks[view, i, j], view

    def sample_depth(self, n: int):
        """Rays and sparse depths (exact pixel coordinates), or None when the scene has none."""
        if self.data.depth_val is None or n <= 0:
            return None
        k = torch.randint(0, self.data.depth_val.numel(), (n,), generator=self.gen, device="cpu")
        k = k.to(self.data.depth_val.device)
        o, d = self.data.rays(self.data.depth_views[k], self.data.depth_uv[k])
        return o, d, self.data.depth_val[k]
