"""Reading a phone's folder as it comes (pipeline/inputs/photos.py): EXIF orientations, HEIC, grayscale, alpha, 16 bits,
duplicate stems; and the synthetic phone folder's roll model."""

import cv2
import numpy as np
import pytest
from PIL import Image

from pipeline.errors import StageError
from pipeline.inputs.photos import list_photos, read_photo, read_upright
from synth.phone import save_jpeg, upright_roll


def _marked(h=30, w=40):
    img = np.zeros((h, w, 3), np.uint8)
    img[2, 5] = (255, 255, 255)  # x = 5, y = 2
    return img


@pytest.mark.parametrize("flag,shape,at", [(1, (30, 40), (5, 2)), (6, (40, 30), (27, 5)), (3, (30, 40), (34, 27)),
                                           (8, (40, 30), (2, 34))])
def test_exif_orientation_is_applied(tmp_path, flag, shape, at):
    p = tmp_path / f"f{flag}.jpg"
    save_jpeg(_marked(), p, flag, quality=100)
    img = read_photo(p)
    assert img.shape[:2] == shape
    y, x = np.unravel_index(img[..., 0].argmax(), img.shape[:2])
    assert (x, y) == at


@pytest.mark.parametrize("flag", [6, 3, 8])
def test_roll_model_matches_the_upright_photo(flag):
    """A point seen at pixel (5.5, 2.5) of the stored image is where the upright photo's rolled camera sees it."""
    K = np.array([[50.0, 0, 20], [0, 50, 15], [0, 0, 1]])
    X = np.linalg.inv(K) @ [5.5, 2.5, 1.0]
    w, h = (30, 40) if flag in (6, 8) else (40, 30)
    Ku = np.array([[50.0, 0, w / 2], [0, 50, h / 2], [0, 0, 1]])
    x = Ku @ upright_roll(np.eye(3), flag) @ X
    expected = {6: (27.5, 5.5), 3: (34.5, 27.5), 8: (2.5, 34.5)}[flag]
    assert np.allclose(x[:2] / x[2], expected)


def test_heic_grayscale_rgba_and_16_bit(tmp_path):
    from pillow_heif import register_heif_opener

    register_heif_opener()
    rgb = cv2.cvtColor(cv2.GaussianBlur((np.random.default_rng(0).random((30, 40, 3)) * 255).astype(np.uint8),
                                        (0, 0), 2), cv2.COLOR_BGR2RGB)
    Image.fromarray(rgb).save(tmp_path / "a.heic", quality=95)
    heic = read_photo(tmp_path / "a.heic")
    assert heic.shape == (30, 40, 3) and np.abs(heic.astype(int) - rgb[..., ::-1]).mean() < 8
    gray = (np.arange(1200).reshape(30, 40) % 256).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    g = read_photo(tmp_path / "g.png")
    assert g.shape == (30, 40, 3) and (g[..., 0] == gray).all() and (g[..., 2] == gray).all()
    rgba = np.dstack([rgb[..., ::-1], np.full((30, 40), 128, np.uint8)])
    cv2.imwrite(str(tmp_path / "r.png"), rgba)
    assert (read_photo(tmp_path / "r.png") == rgb[..., ::-1]).all()  # the colour, alpha dropped
    deep = (rgb[..., ::-1].astype(np.uint16) * 257)
    cv2.imwrite(str(tmp_path / "d.png"), deep)
    d = read_photo(tmp_path / "d.png")
    assert d.dtype == np.uint8 and (d == rgb[..., ::-1]).all()
    small = read_upright(tmp_path / "d.png", 20)
    assert small.shape == (15, 20, 3)
    (tmp_path / "bad.heic").write_bytes(b"not a heic file")
    assert read_photo(tmp_path / "bad.heic") is None


def test_duplicate_stems_are_one_clear_error(tmp_path):
    folder = tmp_path / "photos of my vase"
    folder.mkdir()
    for name in ("IMG_1.jpg", "IMG_1.heic", "IMG_2.png"):
        (folder / name).write_bytes(b"")
    cv2.imwrite(str(folder / "IMG_1.jpg"), _marked())
    cv2.imwrite(str(folder / "IMG_2.png"), _marked())
    from pillow_heif import register_heif_opener

    register_heif_opener()
    Image.fromarray(_marked()).save(folder / "IMG_1.heic")
    with pytest.raises(StageError, match=r"IMG_1.heic and IMG_1.jpg share a name"):
        list_photos(folder)
    (folder / "IMG_1.heic").unlink()
    ok, skipped = list_photos(folder)
    assert [p.name for p in ok] == ["IMG_1.jpg", "IMG_2.png"] and skipped == []


def test_downscale_keeps_a_strip_one_pixel_high():
    """A 4096×1 strip (a panorama slice in the folder) at 400 px: 400×1, not OpenCV's assertion on a side of 0."""
    from pipeline.inputs.photos import downscale

    strip = np.zeros((1, 4096, 3), np.uint8)
    assert downscale(strip, 400).shape == (1, 400, 3)
    assert downscale(np.zeros((300, 400, 3), np.uint8), 400).shape == (300, 400, 3)  # never upscaled, untouched
