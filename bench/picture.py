"""The README picture: four photo | textured-mesh pairs of a workspace's report, two by two, as one JPEG.

    python bench/picture.py work/dtu_scan24 bench/results/dtu_scan24.jpg
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np


def picture(ws: Path, out: Path) -> None:
    pairs = sorted((ws / "report").glob("render_view_*.png"))[:4]
    if len(pairs) < 4:
        sys.exit(f"{ws / 'report'}: fewer than four render_view_*.png (run the report stage first)")
    imgs = [cv2.imread(str(p)) for p in pairs]
    h = min(i.shape[0] for i in imgs)
    imgs = [cv2.resize(i, (round(i.shape[1] * h / i.shape[0]), h), interpolation=cv2.INTER_AREA) for i in imgs]
    w = max(i.shape[1] for i in imgs)
    imgs = [np.pad(i, ((0, 0), (0, w - i.shape[1]), (0, 0)), constant_values=255) for i in imgs]
    grid = np.concatenate([np.concatenate(imgs[:2], 1), np.concatenate(imgs[2:], 1)], 0)
    cv2.imwrite(str(out), grid, [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(f"picture: {out}")


if __name__ == "__main__":
    picture(Path(sys.argv[1]), Path(sys.argv[2]))
