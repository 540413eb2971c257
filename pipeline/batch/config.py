"""Options of ``python -m pipeline batch``."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class BatchConfig:
    """Batch reconstruction on Ray (python -m pipeline batch)."""

    address: str | None = None
    """Ray cluster to run on (auto: the one this node joined); none: a local cluster on this machine."""
    cpus_per_stage: int = 1
    """CPU cores (and torch threads) each stage task asks for."""
    train_gpus: float = 1.0
    """GPUs each training asks for when the cluster has any (0.125: eight share one); 0: train on CPU."""
    spill_to_cpu: bool = True
    """Train on CPU cores instead of queueing when every GPU slot is taken; off: always wait for a GPU."""
    retries: int = 2
    """Retries of a stage whose worker died (killed, out of memory, node lost); a stage's own error is final."""
