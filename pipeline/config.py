"""One typed config per stage, bundled in :class:`Config`, loaded from YAML presets in ``configs/``.

A preset only lists what differs from the defaults below; unknown keys are an error naming the key.
The command-line options of every stage are generated from these dataclasses (their docstrings are the
``--help`` text), and override the preset.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import yaml

from dvr.trainer import TrainConfig

from .cameras_config import CamerasConfig, DepthConfig, MasksConfig, TextureConfig


@dataclass
class MeshConfig:
    """Isosurface extraction and cleaning (stage ``mesh``)."""

    resolution: int = 256
    """Marching-cubes cells per axis over [-1, 1] (fine level)."""
    coarse_factor: int = 4
    """The coarse level is resolution / coarse_factor; only cells near the surface are refined."""
    refine_steps: int = 2
    """Newton steps moving vertices onto the level set (0: off)."""
    min_component_ratio: float = 0.02
    """Drop connected components with fewer faces than this fraction of the largest."""
    footprint: float = 0.03
    """Height above the support plane (working-sphere radii) below which the mesh is the vertical extrusion of its
    cross-section at that height: the object meets its floor or table with the footprint of what stands just above,
    where automatic masks lose the lowest strip to the contact shadow (the lying book from photos: 23.4 → 24.3 dB
    held-out; cow, jar and DTU within ±0.03 dB). 0: off; no effect without a support plane."""
    smooth_iterations: int = 0
    """Taubin smoothing iterations of the clean mesh (0: off)."""
    max_faces: int = 40000
    """Decimate the clean mesh to at most this many faces (quadric edge collapse)."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the written meshes: 'sfm' (the frame of cameras.npz) or 'normalized' (unit sphere)."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu' or 'cuda'."""


@dataclass
class Config:
    """All stage configs."""

    cameras: CamerasConfig = field(default_factory=CamerasConfig)
    """Stage ``cameras``."""
    masks: MasksConfig = field(default_factory=MasksConfig)
    """Stage ``masks``."""
    depth: DepthConfig = field(default_factory=DepthConfig)
    """Stage ``depth``."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """Stage ``train``."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """Stage ``mesh``."""
    texture: TextureConfig = field(default_factory=TextureConfig)
    """Stage ``texture``."""


def _resolve(tp):
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _resolve(args[0]) if len(args) == 1 else tp
    return tp


def from_dict(cls, data: dict, where: str = ""):
    """Build dataclass ``cls`` from a (partial) dict, recursively; unknown keys raise ValueError."""
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise ValueError(f"{where or cls.__name__}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown key(s) {', '.join(where + k for k in unknown)}; known: {', '.join(sorted(names))}")
    kw = {}
    for k, v in data.items():
        tp = _resolve(hints[k])
        if dataclasses.is_dataclass(tp):
            kw[k] = from_dict(tp, v, f"{where}{k}.")
        elif typing.get_origin(tp) is tuple and isinstance(v, list):
            kw[k] = tuple(v)
        else:
            kw[k] = v
    return cls(**kw)


def load_config(path: str | Path | None) -> Config:
    """Defaults, overridden by the YAML file at ``path`` (when given)."""
    if path is None:
        return Config()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: config file not found; pick one of configs/*.yaml")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML ({exc})") from exc
    try:
        return from_dict(Config, data)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from exc


def config_hash(obj) -> str:
    """Stable hash of a stage config (for the up-to-date check)."""
    d = dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]
