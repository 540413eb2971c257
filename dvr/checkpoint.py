"""Saved fields and checkpoints: written atomically (a file is whole or absent), read back with ``weights_only``
(a model file from elsewhere cannot run code when loaded), and a damaged file or another version's named in one
line (ValueError)."""

from __future__ import annotations

import pickle
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from dvr.atomic import save_torch
from dvr.config import FieldConfig
from dvr.fields import Field, make_field


def save_model(path: Path, model: Field, cfg: FieldConfig, scale_mat: np.ndarray, extra: dict | None = None,
               frame: np.ndarray | None = None) -> None:
    """``scale_mat`` maps the field's frame to the SfM frame; ``frame`` maps it to the normalized frame of
    cameras.npz (identity when the field was trained in that frame); the support plane the field is clipped to
    (field frame) is kept too."""
    support = None if model.support is None else model.support.cpu().numpy()
    save_torch({"field": model.state_dict(), "field_config": asdict(cfg), "scale_mat": scale_mat,
                "frame": np.eye(4) if frame is None else frame, "support": support, **(extra or {})}, path)


# what torch.load and the reading of its dict raise on a file that is not what was saved: truncated or empty (a
# disk filled, a copy cut short), another program's file, or a save of another version of this code
_UNREADABLE = (OSError, EOFError, RuntimeError, ValueError, TypeError, KeyError, AttributeError, IndexError,
               pickle.UnpicklingError)


# what a save holds besides tensors and plain Python: numpy arrays (scale_mat, frame, support, numpy's RNG state).
# An array pickles through the function its own __reduce__ names (numpy's private _reconstruct, whose module moved
# from numpy.core to numpy._core in numpy 2): asked of numpy, not spelled out, so no private path is named here.
_NUMPY_GLOBALS = [np.dtype, np.ndarray, np.zeros(1).__reduce__()[0]] + \
    [type(np.dtype(t)) for t in (np.float64, np.float32, np.int64, np.int32, np.uint32, np.uint8, np.bool_)]


def read_saved(path: Path, device: torch.device, keys: tuple[str, ...]) -> dict:
    """The dict ``torch.save`` wrote at ``path``, holding ``keys``; a ValueError naming the file otherwise. Read
    with ``weights_only``: a model file from elsewhere (a colleague, a shared cluster folder) cannot run code when
    loaded, as a full unpickling would let it."""
    try:
        with torch.serialization.safe_globals(_NUMPY_GLOBALS):
            saved = torch.load(path, map_location=device, weights_only=True)
    except _UNREADABLE as exc:
        raise ValueError(f"{path}: damaged or not saved by this trainer ({type(exc).__name__})") from exc
    missing = [k for k in keys if not isinstance(saved, dict) or k not in saved]
    if missing:
        raise ValueError(f"{path}: not saved by this trainer (no {', '.join(missing)})")
    return saved


def load_model(path: Path, device: torch.device) -> tuple[Field, np.ndarray, np.ndarray]:
    """Load a field saved by :func:`save_model`: (field, scale_mat: field frame → SfM frame, frame: field frame →
    normalized frame of cameras.npz). A ValueError naming the file when it is damaged or another version's."""
    ck = read_saved(path, device, ("field", "field_config", "scale_mat"))
    try:
        fc = dict(ck["field_config"])
        fc["plane_res"] = tuple(fc["plane_res"])
        fc["occ_plane_res"] = tuple(fc.get("occ_plane_res", ()))
        model = make_field(FieldConfig(**fc)).to(device)
        model.load_state_dict(ck["field"])
        model.set_support(ck.get("support"))
        scale_mat = np.asarray(ck["scale_mat"], dtype=np.float64).reshape(4, 4)
        frame = np.asarray(ck.get("frame", np.eye(4)), dtype=np.float64).reshape(4, 4)
    except _UNREADABLE as exc:  # a field of another version of this code (fields or weights renamed)
        raise ValueError(f"{path}: a field this version cannot read ({type(exc).__name__})") from exc
    model.eval()
    return model, scale_mat, frame
