"""bench/subset.py (bench.evaluate.take_photos): evenly spaced photos of a folder, optionally enlarged."""

import cv2
import numpy as np
import pytest

from bench.evaluate import take_photos


def _folder(tmp_path, n=10):
    src = tmp_path / "src"
    src.mkdir()
    for i in range(n):
        size = (40, 30) if i % 3 else (30, 40)  # landscape and portrait
        cv2.imwrite(str(src / f"IMG_{i:02d}.png"), np.full((size[1], size[0], 3), 20 * i, np.uint8))
    return src


def test_evenly_spaced_photos_copied_as_they_are(tmp_path):
    src = _folder(tmp_path)
    before = {p.name: p.read_bytes() for p in src.iterdir()}
    out = take_photos(src, tmp_path / "out", 4)
    assert sorted(p.name for p in out.iterdir()) == ["IMG_00.png", "IMG_03.png", "IMG_06.png", "IMG_09.png"]
    assert all((out / n).read_bytes() == before[n] for n in ("IMG_03.png", "IMG_06.png"))
    assert {p.name: p.read_bytes() for p in src.iterdir()} == before  # the source only read


def test_photos_enlarged_to_a_longest_side_at_their_own_aspect(tmp_path):
    out = take_photos(_folder(tmp_path), tmp_path / "out", 3, long_side=400)
    shapes = {p.name: cv2.imread(str(p)).shape[:2] for p in out.iterdir()}
    assert shapes == {"IMG_00.jpg": (400, 300), "IMG_04.jpg": (300, 400), "IMG_09.jpg": (400, 300)}


def test_more_photos_than_the_folder_holds_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="10 photos; --take must be between 2 and that"):
        take_photos(_folder(tmp_path), tmp_path / "out", 11)
