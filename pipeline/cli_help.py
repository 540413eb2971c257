"""The short ``--help`` of a command: its paths, the preset, and the few options a user needs (:data:`USER_OPTIONS`),
one line each. ``--help-all`` prints tyro's listing of every option instead; docs/method.md explains them."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import typing
from pathlib import Path

USER_OPTIONS: tuple[str, ...] = (
    "cameras.max_side", "cameras.video_frames", "cameras.board_square_mm",
    "train.device", "train.iterations", "train.progress",
    "mesh.max_faces", "mesh.drop_unseen", "mesh.frame",
    "texture.size",
    "batch.address", "batch.cpus_per_stage", "batch.train_gpus",
)
"""The options ``--help`` lists, as ``section.field``; every other one is listed by ``--help-all``."""


def field_doc(cls, name: str) -> str:
    """The docstring of field ``name`` of dataclass ``cls`` (the string literal under it), on one line."""
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    for node, after in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", None) == name and \
                isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
            return " ".join(after.value.value.split())
    return ""


def flag(name: str, value=None) -> str:
    """The command-line spelling of option ``name`` (``cameras.max_side`` → ``--cameras.max-side``); a boolean
    option as both of its flags (``--mesh.[no-]drop-unseen``)."""
    *sections, leaf = name.split(".")
    leaf = ("[no-]" if isinstance(value, bool) and sections else "") + leaf.replace("_", "-")
    return "--" + ".".join(sections + [leaf])


def _shown(value) -> str:
    return ("on" if value else "off") if isinstance(value, bool) else str(value)


def _metavar(value, hint=None) -> str:
    if hasattr(hint, "__metadata__"):  # Annotated[T, …]: T
        hint = typing.get_args(hint)[0]
    if typing.get_origin(hint) is typing.Literal:
        return "{" + ",".join(map(str, typing.get_args(hint))) + "}"
    if isinstance(value, bool):
        return ""
    if isinstance(value, (int, float)):
        return type(value).__name__.upper()
    if isinstance(value, tuple):
        return "INT ..."
    if value is None:  # Optional: name it by what it holds
        return "PATH" if Path in typing.get_args(hint) else "TEXT"
    return "PATH" if isinstance(value, Path) else "TEXT"


def _line(spelling: str, text: str) -> str:
    return f"  {spelling:<34} {text}" if len(spelling) < 34 else f"  {spelling}  {text}"


def _arg_help(hint) -> str:
    """The help text a generated field carries (``tyro.conf.arg(help=…)`` in its ``Annotated``)."""
    for meta in getattr(hint, "__metadata__", ()):
        if getattr(meta, "help", None):
            return meta.help
    return ""


def short_help(cls, default, prog: str) -> str:
    """The short help of generated command class ``cls`` whose values are ``default`` (the preset's)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    positional = [f.name for f in dataclasses.fields(cls) if f.name in ("workspace", "captures", "out")]
    usage = " ".join(p.upper() if p != "out" else "[OUT]" for p in positional)
    lines = [f"usage: {prog} {usage} [options]", "", " ".join((cls.__doc__ or "").split()), "", "arguments:"]
    lines += [_line(p.upper(), _arg_help(hints[p])) for p in positional]
    lines += ["", "options:"]
    n_shown = 0
    for f in dataclasses.fields(cls):
        value = getattr(default, f.name, None)
        if f.name in positional:
            continue
        if not dataclasses.is_dataclass(value):
            lines.append(_line(f"{flag(f.name, value)} {_metavar(value, hints[f.name])}".rstrip(),
                               _arg_help(hints[f.name])))
            continue
        section_hints = typing.get_type_hints(type(value))
        for name in [n for n in USER_OPTIONS if n.split(".", 1)[0] == f.name]:
            leaf = name.split(".", 1)[1]
            v = getattr(value, leaf)
            lines.append(_line(f"{flag(name, v)} {_metavar(v, section_hints[leaf])}".rstrip(),
                               f"{field_doc(type(value), leaf)} (now: {_shown(v)})"))
            n_shown += 1
    n_all = sum(len(_leaves(getattr(default, f.name))) for f in dataclasses.fields(cls)
                if dataclasses.is_dataclass(getattr(default, f.name, None)))
    lines += ["", f"--help-all lists every option ({n_all}, of which {n_shown} above), one line each; "
              "docs/method.md explains them."]
    return "\n".join(lines)


def _leaves(cfg) -> list[str]:
    """The option names of a config section, nested sections included."""
    out = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        out += [f"{f.name}.{n}" for n in _leaves(value)] if dataclasses.is_dataclass(value) else [f.name]
    return out
