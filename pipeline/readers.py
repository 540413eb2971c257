"""Reading what earlier stages wrote (the SfM model, the trained model, meshes, the board's units), each with a
one-line error naming the file and the fix when it is damaged."""

from __future__ import annotations

import json
from pathlib import Path

import torch
import trimesh

from dvr.checkpoint import load_model
from pipeline.errors import StageError


def read_stage_model(path: Path):
    """The cameras stage's undistorted COLMAP model at ``path``, as a later stage reads it; StageError naming it when
    pycolmap cannot (a cameras run killed while COLMAP wrote it: the folder comes before its files)."""
    from pipeline.colmaplib import pycolmap

    try:
        return pycolmap.Reconstruction(path)
    except Exception as exc:  # noqa: BLE001 - pycolmap raises ValueError or RuntimeError with COLMAP's own text
        raise StageError(f"{path}: unreadable SfM model ({type(exc).__name__}); rerun the cameras stage "
                         "(cameras --force)") from exc


def mesh_units(root: Path, frame: str) -> dict:
    """What the mesh stage records of its units: metres when the cameras stage found a board and the meshes are in
    the frame of cameras.npz; nothing otherwise."""
    path = root / "board.json"
    if frame != "sfm" or not path.exists():
        return {}
    info = json.loads(path.read_text())
    return {"units": "metres", "board": info.get("board"), "metres_per_sfm_unit": info.get("metres_per_sfm_unit")}


def load_mesh_file(path: Path, file_type: str, what: str, fix: str, **kwargs):
    """``trimesh.load`` of a file a stage wrote (``process=False`` unless given), or a StageError naming it, what it
    should hold and ``fix``, when it is damaged (a killed write, a disk that filled) or not what was written."""
    try:
        return trimesh.load(path, file_type=file_type, **{"process": False, **kwargs})
    except Exception as e:  # noqa: BLE001 - trimesh raises what its parser meets (ValueError, KeyError, struct.error)
        raise StageError(f"{path}: unreadable {what} ({type(e).__name__}); {fix}") from e


def read_model(path, device: torch.device):
    """The trained field of ``model/final.pt`` (:func:`dvr.checkpoint.load_model`: field, scale_mat, frame); a
    StageError naming the file and the fix when it is damaged or another version's."""
    try:
        return load_model(path, device)
    except ValueError as exc:
        raise StageError(f"{exc}; retrain (train --force)") from exc
