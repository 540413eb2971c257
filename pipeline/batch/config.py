"""Options of ``python -m pipeline batch``."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class BatchConfig:
    """Batch reconstruction on Ray (``python -m pipeline batch``)."""

    address: str | None = None
    """Ray cluster to run on (``ray start --head`` prints its address; ``auto``: the cluster this node joined);
    None: start a local Ray cluster on this machine for the batch."""
    cpus_per_stage: int = 1
    """CPU cores each stage task asks for (and its torch threads): on 2 cores, two stages of different captures
    run at once."""
    train_gpus: float = 1.0
    """GPUs the train stage asks for when the cluster has any (its device is then CUDA); a fraction lets that many
    trainings share one GPU (0.125: eight); 0: train on CPU cores. Other stages see no GPU unless set to cuda."""
    spill_to_cpu: bool = True
    """When the GPUs already have a training running and one waiting per slot (1 / ``train_gpus`` slots a GPU), a
    capture ready to train trains on its CPU cores instead of queueing: at the fast preset an H100 trains a capture
    hardly faster than one core, so a node's cores would otherwise wait on its GPU. False: every training waits for a
    GPU."""
    retries: int = 2
    """Retries of a stage whose worker died (killed, out of memory, node lost); a stage's own error is final."""
