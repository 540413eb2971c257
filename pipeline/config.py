"""The config tree: one typed config per stage (each defined next to the code it configures), bundled in
:class:`Config` (built from the stage table), loaded from YAML presets in ``configs/``.

A preset only lists what differs from the defaults below; unknown keys are an error naming the key.
The command-line options of every stage are generated from these dataclasses (their docstrings are the
``--help`` text), and override the preset.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import field
from pathlib import Path

import yaml

from .stages import STAGES

Config = dataclasses.make_dataclass(
    "Config", [(s.name, s.options, field(default_factory=s.options)) for s in STAGES if s.options is not None])
Config.__module__ = __name__  # pickles by name (Ray sends configs to its workers)
Config.__doc__ = """All stage configs: a field per stage of :data:`pipeline.stages.STAGES` that has options, named
after it (``cfg.train.iterations``; YAML ``train: {iterations: …}``; CLI ``--train.iterations``)."""


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


def config_from_args(preset: str | Path | None, options: list[str]) -> Config:
    """The config a command line gives: the YAML ``preset`` (defaults without one) overridden by ``options`` in
    the CLI's spelling (``["--train.iterations", "750", "--texture.view-selection"]``)."""
    import tyro

    return tyro.cli(Config, default=load_config(preset), args=list(options), prog="options")
