"""bench/mask_trust.py: the depth of the run's visual hull in each view's mask background."""

import shutil

import cv2
import numpy as np

from bench.mask_trust import hull_depths


def test_a_mask_missing_a_rim_shows_as_hull_deep_in_its_background(small_ws, tmp_path):
    """One view's mask eroded by 3 px (a mask that misses the object's rim): the two-mask hull, which that view alone
    cannot carve, now reaches about 3 px (× 500 / the 64-px image's diagonal, the probe's 400×300 scale) deeper
    into that view's background; every depth is finite and non-negative."""
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    before = hull_depths(ws, 64)
    mask_path = ws / "masks" / "000000.png"
    cv2.imwrite(str(mask_path), cv2.erode(cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE), np.ones((7, 7), np.uint8)))
    after = hull_depths(ws, 64)
    scale = 500 / np.hypot(64, 64)
    assert len(before) == len(after) == 8 and all(np.isfinite(d).all() and (d >= 0).all() for d in before + after)
    assert after[0].max() - before[0].max() > 2.5 * scale
