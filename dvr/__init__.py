"""DVR: Differentiable Volumetric Rendering (Niemeyer et al., CVPR 2020) on CPU and CUDA.

Modules: ``cameras`` (rays, unit-sphere bounds), ``fields`` (occupancy + texture fields behind the ``Field``
interface, chunked evaluation), ``march`` (surface finding without autograd), ``implicit`` (the exact implicit
depth gradient),
``losses``, ``hull`` (visual hull from masks), ``data`` (workspace loading, ray sampling),
``trainer``, ``checkpoint`` (saved fields, read back safely), ``extract`` (hierarchical marching cubes), ``metrics``.
This package never imports ``pipeline``.
"""

__version__ = "0.1.0"
