"""The training's options: the fields, the loss weights and the trainer (the ``train`` section of the config)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from dvr.options import PositiveFloat, PositiveInt


@dataclass
class FieldConfig:
    """Representation of the occupancy and texture fields."""

    kind: Literal["grid", "mlp"] = "grid"
    """grid: dense occupancy grid, tri-plane texture features and small MLPs (fast); mlp: a plain MLP (reference)."""
    base_res: PositiveInt = 96
    """Resolution of the dense occupancy grid (cells per axis over the working sphere's [-1, 1] cube)."""
    plane_res: tuple[int, ...] = (64, 128, 256)
    """Resolutions of the texture field's tri-plane levels (three planes per level)."""
    occ_plane_res: tuple[int, ...] = ()
    """Resolutions of an optional tri-plane residual of the occupancy; empty: the dense grid alone."""
    plane_features: PositiveInt = 4
    """Feature channels per plane and level."""
    hidden: PositiveInt = 32
    """Width of the small MLP heads (grid) or of every layer (mlp)."""
    mlp_layers: PositiveInt = 4
    """Hidden layers of the reference MLP (kind mlp)."""
    mlp_frequencies: int = 6
    """Fourier frequencies of the reference MLP's position encoding."""
    logit_clamp: float = 10.0
    """Bound on the magnitude of the initial occupancy grid's logits (the hull prior)."""


@dataclass
class LossWeights:
    """Weights of the DVR loss terms (each term is a mean over its samples; 0 turns it off)."""

    rgb: float = 1.0
    """L1 colour loss on rays that hit the surface where the mask is set."""
    freespace: float = 1.0
    """Pushes occupancy to empty along rays outside the mask."""
    occupancy: float = 1.0
    """Pushes occupancy to full on mask rays the rendering misses (and at missed sparse depths)."""
    depth: float = 1.0
    """L1 between rendered and SfM sparse depth; 0 also drops the sparse-depth rays from training."""
    depth_free: float = 1.0
    """Pushes occupancy to empty in front of each sparse depth (space SfM saw through)."""
    carve: float = 1.0
    """Pushes occupancy to empty at random points outside the masks' visual hull."""
    tv: float = 0.0
    """Total variation of the occupancy grids; 0: off."""
    normal: float = 0.05
    """Smoothness of the surface normals at hit points; 0: off."""
    shading: float = 0.05
    """Pull of the view-dependent shading residual towards zero (with view-shading)."""
    appearance: float = 0.01
    """Pull of the per-view colour gains towards 1 (with appearance)."""


@dataclass
class TrainConfig:
    """Training of the DVR occupancy and texture fields (stage train)."""

    iterations: PositiveInt = 1000
    """Optimisation steps."""
    batch_rays: PositiveInt = 2048
    """Pixels (rays) per step."""
    depth_rays: int = 256
    """Extra rays per step through pixels with an SfM sparse depth."""
    depth_free_margin: float = 0.03
    """Free-space points of sparse-depth rays stay this far in front of the depth (working-sphere radii)."""
    carve_points: int = 4096
    """Random points per step for visual-hull carving."""
    n_steps: PositiveInt = 64
    """Ray-marching samples between the working sphere's entry and exit."""
    n_steps_final: PositiveInt = 96
    """Marching samples at the last step (a linear schedule from n-steps)."""
    n_secant: int = 8
    """Secant refinement steps of each ray's surface point."""
    jitter: bool = True
    """Jitter the marching samples while training."""
    cuda_graphs: bool = True
    """On a GPU, replay each step's surface finding as a CUDA graph (faster, same result); no effect on CPU."""
    gpu_batch_scale: PositiveInt = 2
    """On a GPU: this many times the rays and points a step, in as many times fewer steps, the learning rates × its
    square root; 1: the CPU's steps."""
    lr_grid: float = 0.04
    """Adam learning rate of the grids and planes."""
    lr_mlp: float = 0.004
    """Adam learning rate of the MLP heads."""
    lr_appearance: float = 0.01
    """Learning rate of the per-view colour gains (appearance)."""
    lr_decay: float = 0.1
    """Final learning rate as a fraction of the initial one (exponential decay)."""
    grad_eps: float = 0.05
    """Guard on the denominator of the implicit surface gradient (sign-preserving)."""
    boundary_fraction: float = 0.25
    """Fraction of each batch drawn from a band around the mask boundaries."""
    coarse_res: int = 64
    """Start the occupancy grid at this resolution, upsampled at upsample-at; 0: one resolution throughout."""
    upsample_at: float = 0.5
    """Fraction of the iterations after which the coarse occupancy grid is upsampled to field.base-res."""
    fit_frame: bool = True
    """Train in the bounding sphere of the masks' visual hull (× frame-margin), tighter than SfM's sphere."""
    frame_margin: PositiveFloat = 1.15
    """Margin of the fitted working sphere around the visual hull."""
    depth_carve_init: bool = True
    """Carve the initial occupancy free along each sparse-depth ray up to its depth."""
    hull_init: bool = True
    """Initialise the occupancy grid from the masks' visual hull."""
    hull_res: PositiveInt = 64
    """Resolution (cells per axis) of the visual-hull volume."""
    photo_hull: bool = False
    """Start from the photo hull, which also carves what the views disagree on in colour (a cup's hidden inside)."""
    photo_hull_res: PositiveInt = 128
    """Lattice resolution of the photo hull (its cells must be finer than the object's thin parts)."""
    photo_spread: float = 0.005
    """Colour spread (colours 0–1) across the views above which the photo hull carves a point."""
    photo_contrast: float = 1.0
    """The photo hull's carving threshold rises by this × the photos' local contrast at the point."""
    photo_min_depth: float = 0.1
    """The photo hull fills carves shallower than this (working-sphere radii) back in; 0: keep every carve."""
    carve_min_views: int = 2
    """Views that must see a point outside their mask for the hull and the carving to call it empty."""
    carve_sparse_views: int = 5
    """Where fewer than this many views see a point, one view's mask carves it; 0: off."""
    framing: Literal["auto", "on", "off"] = "auto"
    """A point can be object only if min-framing-views photos frame it; auto: on for close-up captures."""
    min_framing_views: PositiveInt = 5
    """With framing on: photos that must frame a point (show it inside the image) for it to be object."""
    framing_cut_share: float = 0.5
    """With framing auto: share of the masks reaching the image's edge above which framing is on."""
    carve_sure_depth: float = 0.0
    """One mask carves a point this deep in its background (fraction of the image diagonal); 0: off."""
    contact_band: float = 0.05
    """Height above the floor (working-sphere radii) where carving needs two masks to agree."""
    appearance: Literal["auto", "on", "off"] = "auto"
    """Fit a colour gain per photo (exposure, white balance); auto: on when the photos' exposure differs."""
    appearance_spread: float = 0.05
    """With appearance auto: the photos' exposure spread (0.05: about 5 %) above which it is on."""
    clipped_level: float = 0.98
    """With appearance or view-shading: photo values (0–1) at or above this count as clipped; above 1: off."""
    view_shading: bool = False
    """Explain highlights that move with the camera by a view-dependent colour that the texture leaves out."""
    hull_gate: bool = True
    """Apply the occupancy loss only where the visual hull allows the object, so one wrong mask is outvoted."""
    hull_gate_px: float = 4.0
    """The hull gate counts a view only where the point projects at least this many pixels from its mask."""
    weights: LossWeights = field(default_factory=LossWeights)
    """Loss weights."""
    field: FieldConfig = field(default_factory=FieldConfig)
    """Field representation."""
    checkpoint_every: PositiveInt = 250
    """Steps between checkpoints (a killed training resumes from the last)."""
    log_every: PositiveInt = 25
    """Steps between lines of log.jsonl."""
    preview_every: int = 500
    """Steps between preview renders; 0: only at the end."""
    seed: int = 0
    """Random seed (fixed for reproducible runs)."""
    device: str = "auto"
    """Device: auto (CUDA when present), cpu or cuda."""
    threads: int = 0
    """CPU threads for torch; 0: torch's default."""
    progress: bool = True
    """Show a progress bar."""
