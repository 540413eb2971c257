"""Held-out photos re-aimed: the small rotation of a held-out camera about its own centre that lines the textured
mesh's render up with the photo, fitted with the mesh and its texture frozen.

A held-out photo's pose comes from SfM, with its own error (about 0.06° on the cow, 0.1–0.4 px on the object),
and rendering the mesh there measures that error as much as the mesh: the GT-camera cow's mesh rendered at poses
off by SfM's measured noise loses 3 dB. Methods whose cameras are estimated are compared after fitting each test
view's pose to the frozen model (the test-time pose alignment of BARF and NeRF--); here only a rotation about the
camera centre (3 numbers, at most :data:`MAX_TURN_PX`), which moves the picture of an object far from the camera
almost as a shift of the camera centre does. Turning a camera about its centre maps its image by the homography
K·Rd·K⁻¹, so :func:`fit_rotation` fits the turn on the warped render at the SfM pose (no second render), and
:func:`reaim` finishes on fresh renders against the figure the PSNR takes: the result is never worse than no turn.
:func:`bench.evaluate.reaimed_psnr` gives the re-aimed figure of every bench row; ``python bench/figures.py reaim``
draws one view.
"""
from __future__ import annotations

import numpy as np

COARSE_SIGMA_PX = 2.0  # first fit on both images blurred by this (a pull from up to a few pixels), ...
FINE_SIGMA_PX = 0.7  # ... then by this (sharper, and the bilinear warp's own blur matters less against it)
MAX_TURN_PX = 8.0  # the most a view is turned (pixels at the image centre); SfM's error is a fraction of a pixel


def fit_rotation(img: np.ndarray, hit: np.ndarray, photo: np.ndarray, mask: np.ndarray, K: np.ndarray,
                 iterations: int = 40) -> np.ndarray:
    """(3, 3) the rotation Rd (camera frame) that best turns a camera rendering ``img`` (H, W, 3; the mesh covers
    ``hit``) at world→camera rotation R into one that sees ``photo`` (H, W, 3; the object covers ``mask``): the
    camera at Rd·R. Least squares over the union of the mask and the turned render's coverage, as the PSNR counts."""
    import torch
    import torch.nn.functional as F
    from kornia.filters import gaussian_blur2d
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix

    h, w = hit.shape
    if img.shape != (h, w, 3) or photo.shape != (h, w, 3) or mask.shape != (h, w) or K.shape != (3, 3):
        raise ValueError(f"fit_rotation: img {img.shape}, hit {hit.shape}, photo {photo.shape}, mask {mask.shape}, "
                         f"K {K.shape}: want (H, W, 3), (H, W), (H, W, 3), (H, W), (3, 3)")
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
    src = torch.cat([t(img).permute(2, 0, 1), t(hit)[None]])[None]  # (1, 4, H, W): colour and coverage
    ref = torch.cat([t(photo).permute(2, 0, 1), t(mask)[None]])[None]
    Kt = t(K)
    jj, ii = torch.meshgrid(torch.arange(w, dtype=torch.float64) + 0.5, torch.arange(h, dtype=torch.float64) + 0.5,
                            indexing="xy")
    pix = torch.stack([jj, ii, torch.ones_like(jj)], -1).reshape(-1, 3)
    Kt_inv = torch.linalg.inv(Kt)
    focal = float(K[0, 0] + K[1, 1]) / 2
    theta = torch.zeros(3, dtype=torch.float64, requires_grad=True)  # the axis-angle times the focal length (px)

    def loss(s: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        Rd = axis_angle_to_rotation_matrix((theta / focal)[None])[0]
        q = pix @ (Kt @ Rd.T @ Kt_inv).T  # where each output pixel's ray lay before the turn
        xy = q[:, :2] / q[:, 2:]
        grid = torch.stack([2 * xy[:, 0] / w - 1, 2 * xy[:, 1] / h - 1], -1).reshape(1, h, w, 2)
        out = F.grid_sample(s, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        cover, m = out[0, 3], r[0, 3]
        union = cover + m - cover * m
        return (union * ((out[0, :3] - r[0, :3]) ** 2).sum(0)).sum() / (h * w)

    for sigma in (COARSE_SIGMA_PX, FINE_SIGMA_PX):
        k = 2 * int(3 * sigma) + 1
        s, r = (gaussian_blur2d(a, (k, k), (sigma, sigma)) for a in (src, ref))
        opt = torch.optim.LBFGS([theta], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

        def closure(opt=opt, s=s, r=r):
            opt.zero_grad()
            e = loss(s, r)
            e.backward()
            return e

        opt.step(closure)
    with torch.no_grad():
        Rd = axis_angle_to_rotation_matrix((theta / focal)[None])[0]
    return Rd.numpy()


def _turn(theta: np.ndarray, focal: float) -> np.ndarray:
    """The rotation of axis-angle ``theta / focal`` (theta in pixels at the image centre)."""
    import cv2

    return cv2.Rodrigues(np.asarray(theta, float) / focal)[0]


def degrees_turned(Rd: np.ndarray) -> float:
    """The angle (degrees) of the rotation ``Rd``."""
    from dvr.metrics import rotation_angle_deg

    return float(rotation_angle_deg(Rd))


def reaim(caster, K: np.ndarray, R: np.ndarray, centre: np.ndarray, photo: np.ndarray, mask: np.ndarray,
          steps_px: tuple[float, ...] = (0.5, 0.25, 0.12, 0.06)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Rd, image, hit): the turn about the camera's centre whose fresh render of ``caster``
    (:class:`pipeline.render.textured.TexturedCaster`) has the least squared error against ``photo`` over ``mask`` ∪ its
    pixels — the figure the PSNR takes — and that render. Starts from the better of no turn and
    :func:`fit_rotation`'s (a fit on warped renders, which bilinear resampling blurs, so not trusted for the last
    fraction of a pixel), then a compass search on fresh renders, one axis at a time, in ``steps_px`` (pixels at the
    image centre; each halving once no step helps). Never worse than no turn."""
    import cv2

    h, w = photo.shape[:2]
    focal = float(K[0, 0] + K[1, 1]) / 2
    img, hit = caster.render(K, R, centre, w, h)
    ys, xs = np.nonzero(mask | hit)
    if not len(ys):
        return np.eye(3), img, hit
    pad = int(np.ceil(MAX_TURN_PX)) + 4  # the box holds every pixel a turn the search may try brings in
    box = (max(0, ys.min() - pad), min(h, ys.max() + pad + 1), max(0, xs.min() - pad), min(w, xs.max() + pad + 1))

    def sse(i, c):
        return float(((i - photo)[mask | c] ** 2).sum())

    def error(theta):
        i, c = caster.render(K, _turn(theta, focal) @ R, centre, w, h, box)
        return sse(i, c), i, c

    best = (np.zeros(3), sse(img, hit), img, hit)  # the box holds every pixel of the render at no turn
    start = cv2.Rodrigues(fit_rotation(img, hit, photo, mask, K))[0].ravel() * focal
    if np.linalg.norm(start) <= MAX_TURN_PX and (tried := (start, *error(start)))[1] < best[1]:
        best = tried
    for step in steps_px:
        better = True
        while better:
            better = False
            for axis in range(3):
                for sign in (1.0, -1.0):
                    theta = best[0].copy()
                    theta[axis] += sign * step
                    if np.linalg.norm(theta) > MAX_TURN_PX:
                        continue
                    if (tried := (theta, *error(theta)))[1] < best[1]:
                        best, better = tried, True
    return _turn(best[0], focal), best[2], best[3]
