"""Synthetic scene description: plain data (YAML ↔ dataclasses).

A scene lists its shape, albedo, background, lighting and optional effects; the renderer computes only
what is listed (``render.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import yaml


@dataclass
class Shape:
    """Geometry in the canonical frame (object inside the unit sphere)."""

    kind: str = "torus"
    """sphere | box | torus | cylinder (upright, half height size[2], edges rounded by minor) | shell | union |
    difference (the first part less the others: a cup is a cylinder less a narrower one above its floor) |
    mesh."""
    radius: float = 0.5
    """sphere radius; torus major radius; shell outer radius."""
    minor: float = 0.2
    """torus minor radius; shell thickness."""
    size: list[float] = field(default_factory=lambda: [0.4, 0.4, 0.4])
    """box half extents."""
    center: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    """offset of the primitive."""
    axis: str = "z"
    """torus and cylinder: the axis they turn about, 'x', 'y' or 'z' (a mug's handle is a torus about 'y')."""
    parts: list[dict] = field(default_factory=list)
    """union, difference: a list of Shape dicts."""
    path: str = ""
    """mesh: an OBJ/PLY file; relative paths are relative to the scene file."""
    fit_radius: float = 0.8
    """mesh: scale so its bounding sphere has this radius (centred at the origin)."""
    up: str = "z"
    """mesh: the file's up axis, 'z' (used as is) or 'y' (rotated so that +y points up, +z in the scene)."""
    relief: float = 0.0
    """analytic shapes: height of bumps raised on the surface (canonical units; 0: none), a knobbly, hammered
    surface: the distance less relief · sin(2π·relief_scale·x) sin(…y) sin(…z)."""
    relief_scale: float = 12.0
    """analytic shapes: bumps per unit length along each axis (one bump and one dip per period)."""


@dataclass
class Albedo:
    """The object's surface colour."""

    kind: str = "checker"
    """constant | checker | noise | texture (mesh UV texture)."""
    color: list[float] = field(default_factory=lambda: [0.8, 0.5, 0.3])
    """constant colour / first checker colour."""
    color2: list[float] = field(default_factory=lambda: [0.2, 0.3, 0.7])
    """second checker colour."""
    scale: float = 6.0
    """checker cells / noise frequency per unit length."""
    levels: int = 0
    """noise: quantise to this many levels per channel (sharp edges for SfM; 0 = smooth)."""
    contrast: float = 1.0
    """noise: 1 = the full colour noise; below 1 it is blended towards ``color`` (a weakly textured surface)."""
    seed: int = 1


@dataclass
class Background:
    """What the views see behind the object."""

    kind: str = "none"
    """none (black) | constant | backdrop (textured sphere around the scene, for SfM features)."""
    color: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    radius: float = 6.0
    """backdrop sphere radius (canonical units)."""
    scale: float = 3.0
    """backdrop noise frequency."""
    levels: int = 4
    """backdrop noise quantisation levels (sharp edges for SfM)."""
    saturation: float = 1.0
    """backdrop colour saturation (0: grey)."""
    seed: int = 2


@dataclass
class Lighting:
    """Shading of the object (none: albedo only)."""

    kind: str = "none"
    """none (albedo only) | lambertian."""
    ambient: float = 0.35
    lights: list[list[float]] = field(default_factory=lambda: [[0.4, 0.5, 0.8, 0.7]])
    """directional lights: [dx, dy, dz, intensity]."""


@dataclass
class Effect:
    """One photographic effect applied to the renders (``kind`` and its parameters)."""

    kind: str = "noise"
    """noise (sigma) | exposure (amount: max relative gain change; white_balance: max relative change of each
    colour channel's gain on top; the gains of every view are written to ``gt/exposure.json``) | distortion (k1) |
    blur (sigma px) |
    specular (amount, shininess) | ground (pattern, scale, color, color2, shadow, softness, sink, normal, seed: a
    plane the object rests on or hangs from, see ``ground.py``; board, board_*, metres_per_unit: a printed ChArUco
    board on it)."""
    sigma: float = 0.01
    amount: float = 0.2
    white_balance: float = 0.0
    """exposure: max relative change of each colour channel's gain (auto white balance), on top of ``amount``."""
    k1: float = 0.0
    shininess: float = 32.0
    pattern: str = "wood"
    """ground: wood | tiles | checker | noise."""
    scale: float = 4.0
    """ground: planks / tiles / checker cells per unit length (noise: frequency)."""
    color: list[float] = field(default_factory=lambda: [0.55, 0.36, 0.2])
    """ground: first colour of the pattern."""
    color2: list[float] = field(default_factory=lambda: [0.8, 0.62, 0.42])
    """ground: second colour of the pattern."""
    shadow: float = 0.6
    """ground: strength of the contact shadow (darkening of the ambient light at the object), 0..1."""
    softness: float = 0.08
    """ground: radius of the contact shadow (canonical units)."""
    sink: float = 0.004
    """ground: how far the object sinks into the plane (so it touches wherever it rests)."""
    normal: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])
    """ground: the plane's normal (canonical frame), towards the object: [0, 0, 1] a floor under it, [1, 0, 0] a
    wall at its back (its side of smallest x) that it hangs on; the plane touches the object's far side."""
    board: list[int] = field(default_factory=list)
    """ground: squares (columns, rows) of a printed ChArUco board lying on it, centred under the object, its rows
    along x, on white paper 15 mm wider all round ([]: no board; see ``pipeline/cameras/board.py``)."""
    board_square_mm: float = 35.0
    """ground: side of a board square (mm)."""
    board_marker_mm: float = 26.0
    """ground: side of a board marker (mm)."""
    board_dictionary: str = "DICT_4X4_50"
    """ground: ArUco dictionary of the board."""
    metres_per_unit: float = 0.1
    """ground with a board: metres per canonical unit (the board's printed size fixes the scene's scale; written to
    ``gt/board.json``)."""
    seed: int = 3


@dataclass
class CameraRig:
    """The views: how many, image size, distance, field of view and layout around the object."""

    n_views: int = 24
    width: int = 128
    height: int = 128
    radius: float = 2.6
    """distance of the cameras to the origin (canonical units)."""
    fov_deg: float = 40.0
    elevation: list[float] = field(default_factory=lambda: [-20.0, 50.0])
    """min/max elevation in degrees (views on a spiral)."""
    azimuth: list[float] = field(default_factory=lambda: [0.0, 360.0])
    """min/max azimuth in degrees (about z, from +x): the views spread over [min, max) as a full orbit spreads them
    over [0, 360); less than a full turn photographs an object on a wall from its front only."""
    rings: int = 0
    """0: views on a spiral; k > 0: k rings of views at elevations evenly spaced over ``elevation``."""
    orbit_turns: float = 0.0
    """> 0: the views are the frames of a video, one continuous path (``rings`` ignored): this many turns around the
    object while the elevation rises evenly from the first to the second of ``elevation``."""
    supersample: int = 1
    """odd k: k × k samples per pixel, box-filtered (anti-aliasing, as a real lens and sensor integrate)."""
    photo_scale: int = 1
    """odd k: the photos are stored at k × (width, height), as a phone's sensor has many more pixels than the
    stages' working size (``images/``, and the held-out views' in ``gt/heldout/photos/``); the ground truth
    (cameras, masks, depth, ``gt/heldout/images/``) stays at (width, height), each of its pixels the mean of k × k
    photo pixels. For runs from photos (the cameras stage shrinks them); not with ``distortion``."""
    heldout: int = 0
    """extra views (between the training views) written to gt/heldout for evaluation."""
    seed: int = 0


@dataclass
class Scene:
    """A synthetic capture: object, colours, background, lighting, effects, cameras and what is written."""

    name: str = "scene"
    shape: Shape = field(default_factory=Shape)
    albedo: Albedo = field(default_factory=Albedo)
    background: Background = field(default_factory=Background)
    lighting: Lighting = field(default_factory=Lighting)
    effects: list[Effect] = field(default_factory=list)
    cameras: CameraRig = field(default_factory=CameraRig)
    world_scale: float = 1.0
    """size of the canonical unit in 'SfM' units (tests of extreme scales)."""
    world_offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    sparse_depth: int = 0
    """points per view written to depth/ (0: none)."""
    write_masks: bool = True
    """write GT masks into masks/ (as user masks would be)."""
    base_dir: str = ""
    """folder of the scene file (set by load_scene)."""


def _build(cls, data: Any):
    if not is_dataclass(cls):
        return data
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise ValueError(f"expected a mapping for {cls.__name__}, got {data!r}")
    known = {f.name: f for f in fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} keys: {sorted(unknown)} (known: {sorted(known)})")
    kw = {}
    for k, v in data.items():
        ft = known[k].type
        sub = {"shape": Shape, "albedo": Albedo, "background": Background, "lighting": Lighting,
               "cameras": CameraRig}.get(k)
        if cls is Scene and k == "effects":
            kw[k] = [_build(Effect, e) for e in (v or [])]
        elif cls is Scene and sub is not None:
            kw[k] = _build(sub, v)
        else:
            kw[k] = v
        del ft
    return cls(**kw)


def scene_from_dict(d: dict, base_dir: str | Path = ".") -> Scene:
    """A :class:`Scene` from a mapping (a scene file's content; unknown keys are errors); ``base_dir``: the folder
    relative paths (a mesh) start from."""
    s = _build(Scene, d)
    s.base_dir = str(base_dir)
    return s


def load_scene_file(path: str | Path) -> Scene:
    """A :class:`Scene` from a YAML scene file (relative paths in it start from its folder)."""
    path = Path(path)
    try:
        d = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ValueError(f"{path}: cannot read scene ({exc.strerror or type(exc).__name__})") from exc
    except yaml.YAMLError as exc:
        from pipeline.config import yaml_problem

        raise ValueError(f"{path}: not valid YAML ({yaml_problem(exc)}); start from configs/scenes/*.yaml") from exc
    try:
        return scene_from_dict(d or {}, path.parent)
    except ValueError as exc:  # what the scene's keys and values are wrong in, named with the file
        raise ValueError(f"{path}: {exc}") from exc
