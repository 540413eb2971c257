"""The trainer's surface finding, replayed as CUDA graphs on a GPU.

A training step's march and secant are some 300 small kernels; on a GPU their launches, not their arithmetic, set
the time (on an H100 a default step's surface finding takes 6.5 ms eagerly and 0.53 ms replayed as one graph,
``python bench/gpu.py graph DIR``). On CUDA,
:class:`SurfaceFinder` captures :func:`dvr.march.find_surface_fixed` once per shape and set of field tensors as one
CUDA graph and replays it; on CPU it runs :func:`dvr.march.find_surface` eagerly. Both draw the marching jitter
from the same generator in the same order, so a step finds the same surfaces either way.

A graph reads the field's tensors where they were at capture: the optimizer updates them in place, which it sees;
a tensor replaced (the occupancy grid upsampled, the support plane moved to the device) changes the key, and the
next call captures again.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from typing import Callable

import torch

from dvr.march import LogitFn, SurfaceResult, find_surface, find_surface_fixed, sample_fractions

log = logging.getLogger(__name__)

_FIELDS = ("depth", "status", "near", "far", "max_depth")


class _Captured:
    """One CUDA graph of ``find_surface_fixed`` with its static inputs and outputs."""

    def __init__(self, logit_fn: LogitFn, origins: torch.Tensor, dirs: torch.Tensor, fractions: torch.Tensor,
                 n_secant: int, level: float):
        self.origins, self.dirs, self.fractions = origins.clone(), dirs.clone(), fractions.clone()
        side = torch.cuda.Stream(device=origins.device)
        side.wait_stream(torch.cuda.current_stream(origins.device))
        with torch.cuda.stream(side):  # warm-up off the capture: libraries allocate their workspaces here
            for _ in range(2):
                find_surface_fixed(logit_fn, self.origins, self.dirs, self.fractions, n_secant, level)
        torch.cuda.current_stream(origins.device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.result = find_surface_fixed(logit_fn, self.origins, self.dirs, self.fractions, n_secant, level)

    def __call__(self, origins: torch.Tensor, dirs: torch.Tensor, fractions: torch.Tensor) -> SurfaceResult:
        self.origins.copy_(origins)
        self.dirs.copy_(dirs)
        self.fractions.copy_(fractions)
        self.graph.replay()
        # copies: the next replay overwrites the graph's outputs while the step may still read these
        return SurfaceResult(*(getattr(self.result, k).clone() for k in _FIELDS))


class SurfaceFinder:
    """``find_surface`` for a field that changes in place between calls (the trainer's occupancy).

    ``tensors`` lists the tensors ``logit_fn`` reads (parameters, buffers, the support plane); a graph is kept per
    (rays, samples, dtype, those tensors' addresses), at most ``keep`` of them (the oldest go). ``graphs`` False, or
    a CPU device, runs :func:`find_surface`; a graph that cannot be captured (a field that waits for the device)
    logs one warning and the finder runs eagerly from then on."""

    def __init__(self, logit_fn: LogitFn, tensors: Callable[[], list[torch.Tensor | None]], n_secant: int,
                 graphs: bool = True, level: float = 0.0, keep: int = 4):
        self.logit_fn, self.tensors, self.n_secant, self.level = logit_fn, tensors, n_secant, level
        self.graphs_on, self.keep = graphs, keep
        self.graphs: OrderedDict[tuple, _Captured] = OrderedDict()
        self.captures = 0
        """How many graphs were captured so far (a graph replaced after the field's tensors moved counts again)."""

    def __call__(self, origins: torch.Tensor, dirs: torch.Tensor, n_steps: int, jitter: bool) -> SurfaceResult:
        """The first surface along each ray (B, 3), as :func:`find_surface` with ``n_steps`` samples and jitter
        drawn from torch's default generator of the rays' device."""
        if not (self.graphs_on and origins.device.type == "cuda"):
            return find_surface(self.logit_fn, origins, dirs, n_steps=n_steps, n_secant=self.n_secant,
                                level=self.level, jitter=jitter)
        fractions = sample_fractions(origins.shape[0], n_steps, jitter, origins.device, origins.dtype)
        key = (origins.shape[0], n_steps, origins.dtype, self._addresses())
        if key not in self.graphs:
            with torch.no_grad():  # tensors the field moves on its first call (the support plane) move now
                self.logit_fn(origins[:1])
            key = key[:3] + (self._addresses(),)
        graph = self.graphs.get(key)
        if graph is None:
            try:
                graph = _Captured(self.logit_fn, origins, dirs, fractions, self.n_secant, self.level)
            except RuntimeError as err:  # a field that cannot be captured: eager from now on
                log.warning("surface finding as a CUDA graph failed (%s); it runs eagerly", str(err).splitlines()[0])
                self.graphs_on = False
                self.graphs.clear()
                return find_surface_fixed(self.logit_fn, origins, dirs, fractions, self.n_secant, self.level)
            self.captures += 1
            self.graphs[key] = graph
            while len(self.graphs) > self.keep:
                self.graphs.popitem(last=False)
        self.graphs.move_to_end(key)
        return graph(origins, dirs, fractions)

    def _addresses(self) -> tuple:
        return tuple((t.data_ptr(), t.device.index, tuple(t.shape)) for t in self.tensors() if t is not None)
