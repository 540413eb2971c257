"""The config tree: one typed config per stage (each defined next to the code it configures, in the stage's
``config.py``; the train stage's in ``dvr/config.py``), bundled in :class:`Config`, loaded from YAML presets in
``configs/``.

A preset only lists what differs from the defaults; unknown keys are an error naming the key. The command-line
options of every stage are generated from these dataclasses (their docstrings are the ``--help`` text), and
override the preset. Range rules are declared on the fields (:mod:`dvr.options`).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from dvr.config import TrainConfig
from dvr.device import resolve_device
from dvr.options import is_fraction, is_positive
from pipeline.cameras.config import CamerasConfig
from pipeline.depth.config import DepthConfig
from pipeline.masks.config import MasksConfig
from pipeline.mesh.config import MeshConfig
from pipeline.texture.config import TextureConfig


@dataclass
class Config:
    """All stage configs: a field per stage of :data:`pipeline.stages.STAGES` that has options, named after it
    (``cfg.train.iterations``; YAML ``train: {iterations: …}``; CLI ``--train.iterations``)."""

    cameras: CamerasConfig = field(default_factory=CamerasConfig)
    """Camera estimation (stage ``cameras``)."""
    masks: MasksConfig = field(default_factory=MasksConfig)
    """Object masks (stage ``masks``)."""
    depth: DepthConfig = field(default_factory=DepthConfig)
    """Sparse depth from the SfM tracks (stage ``depth``)."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """DVR training (stage ``train``)."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """Mesh extraction and cleaning (stage ``mesh``)."""
    texture: TextureConfig = field(default_factory=TextureConfig)
    """UV texture from the photos (stage ``texture``)."""


def _resolve(tp):
    """The type an option holds: ``T`` of ``Optional[T]`` and of ``Annotated[T, …]`` (a range marker)."""
    if hasattr(tp, "__metadata__"):
        return _resolve(typing.get_args(tp)[0])
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
        elif typing.get_origin(tp) is typing.Literal and isinstance(v, bool) and {"on", "off"} <= set(
                typing.get_args(tp)):
            kw[k] = "on" if v else "off"  # YAML 1.1 reads a bare on / off as true / false
        else:
            kw[k] = v
    return cls(**kw)


def yaml_problem(exc: yaml.YAMLError) -> str:
    """PyYAML's error in one line, the problem and where (its str() spans five: a context and a caret drawing)."""
    mark = getattr(exc, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return where + (getattr(exc, "problem", None) or type(exc).__name__)


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
        raise ValueError(f"{path}: not valid YAML ({yaml_problem(exc)}); fix it or start from configs/default.yaml") \
            from exc
    try:
        cfg = from_dict(Config, data)
        check_config(cfg)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from exc
    return cfg


def _rule_broken(tp, value, positive: bool, fraction: bool = False) -> str | None:
    """What ``value`` of an option of type ``tp`` (``positive``: declared above 0, ``fraction``: declared within
    [0, 1], :mod:`dvr.options`) must be, when it is not; None when it is fine."""
    if tp is bool:
        return None if isinstance(value, bool) else "true or false"
    if tp is int:
        ok = isinstance(value, int) and not isinstance(value, bool) and value >= (1 if positive else 0)
        return None if ok else "a whole number " + ("≥ 1" if positive else "≥ 0")
    if tp is float and fraction:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 <= value <= 1.0
        return None if ok else "a number from 0 to 1"
    if tp is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and \
            (value > 0 if positive else value >= 0)
        return None if ok else "a finite number " + ("> 0" if positive else "≥ 0")
    if tp is str:
        return None if isinstance(value, str) else "text"
    if typing.get_origin(tp) is typing.Literal:
        return None if value in typing.get_args(tp) else "one of " + ", ".join(map(str, typing.get_args(tp)))
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        length = None if Ellipsis in args else len(args)  # tuple[int, ...]: any length
        ok = isinstance(value, tuple) and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1
                                              for v in value) and length in (None, len(value))
        return None if ok else "a list of whole numbers ≥ 1" + ("" if length is None else f" ({length} of them)")
    return None


def check_config(cfg, where: str = "", here: bool = False) -> None:
    """ValueError, one line naming the option, its value and what it must be, for an option of a config (the whole
    :class:`Config` or a stage's section, ``where`` its prefix: ``"texture."``) of the wrong type or out of range
    (the range rules declared on the fields, :mod:`dvr.options`): a YAML preset can hold anything, and a negative size
    or a NaN would fail deep inside a stage, after the stages before it have run. ``here``: the stages run on this
    machine, so a ``device`` it lacks is named too (not when a preset is read: a batch's head node may have no GPU
    where its workers do)."""
    hints = typing.get_type_hints(type(cfg), include_extras=True)
    for f in dataclasses.fields(cfg):
        hint = hints[f.name]
        name, value, tp = where + f.name, getattr(cfg, f.name), _resolve(hint)
        if dataclasses.is_dataclass(tp):
            if not isinstance(value, tp):
                raise ValueError(f"{name}: expected a mapping of its options, got {value!r}")
            check_config(value, name + ".", here)
            continue
        rule = _rule_broken(tp, value, is_positive(hint), is_fraction(hint))
        if rule is not None:
            raise ValueError(f"--{name.replace('_', '-')} = {value!r}: must be {rule} (fix it on the command line "
                             "or in the YAML preset)")
        if here and f.name == "device":  # a device this machine lacks, before a stage runs (not after training)
            try:
                resolve_device(value)
            except ValueError as exc:
                raise ValueError(f"--{name.replace('_', '-')}: {exc}") from exc


def config_from_args(preset: str | Path | None, options: list[str]) -> Config:
    """The config a command line gives: the YAML ``preset`` (defaults without one) overridden by ``options`` in
    the CLI's spelling (``["--train.iterations", "750", "--texture.view-selection"]``)."""
    import tyro

    return tyro.cli(Config, default=load_config(preset), args=list(options), prog="options")
