"""Device selection shared by every entry point (``device: auto``)."""

from __future__ import annotations

import torch


def resolve_device(name: str = "auto") -> torch.device:
    """Return the torch device for ``name`` ("auto" picks CUDA when present, else CPU); a ValueError (a user's
    option, not a fault) for CUDA on a machine without it."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as exc:  # torch's message lists some thirty device types
        raise ValueError(f"device '{name}' is not a torch device; use device: auto, cpu or cuda") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device '{name}' requested but CUDA is not available; use device: auto or cpu")
    return dev
