"""The training's options: the fields, the loss weights and the trainer (the ``train`` stage's section of the
config)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from dvr.options import PositiveFloat, PositiveInt


@dataclass
class FieldConfig:
    """Representation of the occupancy and texture fields."""

    kind: Literal["grid", "mlp"] = "grid"
    """'grid': dense logit grid + tri-plane features + small MLPs (fast); 'mlp': plain MLP reference."""
    base_res: PositiveInt = 96
    """Resolution of the dense occupancy logit grid (cells per axis over [-1, 1])."""
    plane_res: tuple[int, ...] = (64, 128, 256)
    """Resolutions of the texture field's tri-plane levels (one set of three planes per level)."""
    occ_plane_res: tuple[int, ...] = ()
    """Resolutions of an optional tri-plane residual of the occupancy (empty: the dense grid alone)."""
    plane_features: PositiveInt = 4
    """Feature channels per plane and level."""
    hidden: PositiveInt = 32
    """Width of the small MLP heads (grid) or of every layer (mlp)."""
    mlp_layers: PositiveInt = 4
    """Hidden layers of the reference MLP."""
    mlp_frequencies: int = 6
    """Fourier frequencies of the reference MLP's xyz encoding."""
    logit_clamp: float = 10.0
    """|logit| bound of the initial dense grid (hull prior)."""


@dataclass
class LossWeights:
    """Weights of the DVR loss terms (each term is a mean, so weights do not depend on the batch size). Each field
    weights the term of the same name in :meth:`Trainer.losses` (``terms[name]``, logged unweighted under that
    name)."""

    rgb: float = 1.0
    """Term ``rgb`` (:func:`dvr.losses.rgb_loss`): L1 colour loss on rays that hit where the mask is set."""
    freespace: float = 1.0
    """Term ``freespace`` (:func:`dvr.losses.freespace_loss` at :meth:`Trainer.freespace_points`): BCE→0 for rays
    outside the mask (at the hit point, or a random point of a missing ray)."""
    occupancy: float = 1.0
    """Term ``occupancy`` (:func:`dvr.losses.occupancy_loss` at :meth:`Trainer.occupancy_points` and the missed
    sparse-depth points): BCE→1 for mask rays the rendering misses (at the max-logit sample, or at the sparse
    depth)."""
    depth: float = 1.0
    """Term ``depth`` (:func:`dvr.losses.depth_loss`): L1 between rendered and sparse SfM depth (only where depth/
    exists; 0 also skips sampling the sparse-depth rays, so ``occupancy`` and ``depth_free`` lose them too)."""
    depth_free: float = 1.0
    """Term ``depth_free`` (:func:`dvr.losses.freespace_loss`): BCE→0 at a random point of a sparse-depth ray in
    front of its depth (free space seen by SfM)."""
    carve: float = 1.0
    """Term ``carve`` (:func:`dvr.losses.freespace_loss` at :meth:`Trainer.carve_points`): BCE→0 at random points of
    the unit sphere outside the visual hull of the masks."""
    tv: float = 0.0
    """Term ``tv`` (:meth:`dvr.fields.Field.tv_loss`): total variation of the occupancy grids (off: hull init and
    carving already keep space clean, and it flattens the logit ramp where no ray looks)."""
    normal: float = 0.05
    """Term ``normal`` (:meth:`Trainer.normal_loss`): normal smoothness |n(p̂) − n(p̂ + noise)| on hit points (0:
    not computed)."""
    shading: float = 0.05
    """Term ``shading`` (:meth:`dvr.shading.ViewShading.regulariser`): L1 pull of the view-dependent residual towards
    zero (with ``TrainConfig.view_shading``; 0 without)."""
    appearance: float = 0.01
    """Term ``appearance`` (:meth:`dvr.appearance.ViewAppearance.regulariser`): pull of the per-view colour
    transforms towards identity (mean squared log-gain; with ``TrainConfig.appearance``)."""


@dataclass
class TrainConfig:
    """Training of the DVR occupancy and texture fields."""

    iterations: PositiveInt = 1500
    """Optimisation steps."""
    batch_rays: PositiveInt = 2048
    """Pixels (rays) per step."""
    depth_rays: int = 256
    """Extra rays per step through sparse-depth pixels (when depth/ exists)."""
    depth_free_margin: float = 0.03
    """Free-space points of sparse-depth rays stay this far (working-frame units) in front of the depth."""
    carve_points: int = 4096
    """Random points per step for visual-hull carving."""
    n_steps: PositiveInt = 64
    """Ray-marching samples between the unit-sphere entry and exit."""
    n_steps_final: PositiveInt = 96
    """Marching samples at the last step (linear schedule from n_steps)."""
    n_secant: int = 8
    """Secant (Illinois) refinement steps."""
    jitter: bool = True
    """Jitter the marching samples while training."""
    cuda_graphs: bool = True
    """On a GPU, replay each step's surface finding (march and secant) as a CUDA graph: the same surfaces, fewer
    kernel launches (the cow's default training on an H100: 31.9 → 28.9 s); no effect on CPU."""
    lr_grid: float = 0.02
    """Adam learning rate of the grids and planes."""
    lr_mlp: float = 0.002
    """Adam learning rate of the MLP heads."""
    lr_appearance: float = 0.01
    """Learning rate of the per-view colour transforms (``appearance``): a few numbers per photo that must settle
    within the first few hundred steps, before the texture field takes the differences in."""
    lr_decay: float = 0.1
    """Final LR as a fraction of the initial (exponential decay)."""
    grad_eps: float = 0.05
    """Guard of |∇ₚf·w| in the implicit gradient (sign-preserving)."""
    boundary_fraction: float = 0.25
    """Fraction of each batch drawn from a band around mask boundaries."""
    coarse_res: int = 64
    """Start the dense occupancy grid at this resolution and upsample it to field.base_res at
    ``upsample_at`` × iterations (coarse to fine: a coarse grid converges in fewer steps; 0, or a value
    ≥ field.base_res: one resolution throughout)."""
    upsample_at: float = 0.5
    """Fraction of the iterations after which the coarse occupancy grid is upsampled."""
    fit_frame: bool = True
    """Train in a tighter unit sphere: the bounding sphere of the masks' visual hull × frame_margin (the
    normalised frame of SfM is sized from all sparse points, background included)."""
    frame_margin: PositiveFloat = 1.15
    """Margin of the fitted working sphere around the visual hull."""
    depth_carve_init: bool = True
    """Carve the initial (hull) occupancy along every sparse-depth ray up to its depth: the space between a
    camera and a point it observes is free (what masks cannot remove when the object fills the frame)."""
    hull_init: bool = True
    """Initialise the occupancy grid from the visual hull of the masks."""
    hull_res: PositiveInt = 64
    """Resolution of the visual-hull volume."""
    photo_hull: bool = False
    """Start from the photo hull instead of the visual hull (:mod:`dvr.photohull`): carve away what the views
    that see it disagree on in colour, such as the lid over a cup's inside, which no silhouette removes and the
    depth gradient, acting along each ray locally, does not open. Counts go to ``model/photo_hull.json``."""
    photo_hull_res: PositiveInt = 128
    """Lattice resolution of the photo hull: its cell must be finer than the object's thin parts (a cup's wall,
    a handle), whose every point is a surface point at a coarse one."""
    photo_spread: float = 0.005
    """Colour spread (colours in [0, 1]; the mean absolute deviation from the median colour across the views that
    see a point) above which the photo hull carves a point; 6 × this capture's median spread when that is higher."""
    photo_contrast: float = 1.0
    """The photo hull's carving threshold rises by this × the photos' local contrast at the point (a textured
    surface read a pixel off disagrees more than a smooth one)."""
    photo_min_depth: float = 0.1
    """The photo hull puts back a carved region that reaches less than this (working-sphere radii) into the
    visual hull: the nibbles a textured surface loses to its own texture, not a concavity (0 keeps every carve)."""
    carve_min_views: int = 2
    """Views that must see a point outside their mask (all that see it, when fewer do) before the visual hull (the
    initial occupancy, the training frame) and the carving term call it empty. 2 (stop 52; was 1): one photo's
    mask that misses a thin part (an ear tip GrabCut cut) or reads a silhouette a pixel tight cut it for every
    view; held out from photos the cow gained 1.0 dB, the jar 2.6, the floating cow 2.5, DTU lost 0.09 (README,
    "Stop 52: two masks to carve"). The cost is geometry where one silhouette carves by right: the cow's F-score
    0.006–0.018 lower (exact masks: of the cow's surface off by more than 1 % of the diagonal, 58 % is where one
    view alone calls it background), and at the sphere's edge, which only 2–4 views see, the stool from photos kept
    two floaters (Chamfer 0.37 → 1.15 %; ``carve_sparse_views`` below). The mask loss still uses every view's mask."""
    carve_sparse_views: int = 5
    """Where fewer than this many views see a point (the working sphere's edge, which only a few photos frame), one
    view's mask outside carves it whatever ``carve_min_views`` asks: two of the few masks that see such a point
    rarely agree, and the two-mask rule left floaters there (stop 53: the stool from photos 28.72 → 28.99 dB,
    Chamfer 1.15 → 0.41 %; the cow, the floating cow and every scene with GT cameras unchanged, the jar −0.11 dB;
    0: off)."""
    framing: Literal["auto", "on", "off"] = "auto"
    """Whether a point needs ``min_framing_views`` photos that frame it (project it inside the image, whatever their
    masks say) before the visual hull and the carving term may call it occupied: one photo or two cannot place a
    surface in depth, and close-up photos, in which the object leaves the frame, leave much of the working sphere in
    a few frames only: floaters grow there that only those photos see, in front of the object (the cow photographed
    from 1.6 instead of 2.6 with its true cameras and masks: 18.2 → 26.8 dB held out, Chamfer 4.1 → 0.56 %; README,
    "Close-up photos"). auto: on when the object leaves the frame in more than ``framing_cut_share`` of the photos
    (their masks reach the image's edge: DTU, close-ups), off otherwise; off: only a point no photo frames is empty."""
    min_framing_views: PositiveInt = 5
    """With ``framing`` on: how many photos must frame a point (at most all of them are asked for)."""
    framing_cut_share: float = 0.5
    """With ``framing`` auto: the share of the photos whose mask reaches the image's edge (along more than 1 % of
    the border) above which it is on. The bench's captures that frame the object measure 0–15 %, DTU and the
    close-up cow 100 %."""
    carve_sure_depth: float = 0.0
    """How far into a view's background (from its mask's nearest object pixel, as a fraction of the image's diagonal;
    0.01 is 5 px at 400×300) a point must lie for that view's mask alone to carve it, whatever ``carve_min_views``
    asks. 0: off (the default). Stop 54 measured 0.01 on the bench's 18 plain rows: from photos the cow +0.38 dB,
    the jar +0.43, DTU +0.06, but the floating cow −0.79 (one automatic mask misses a part of it by up to 15 px) and
    the book −0.22; with GT cameras the jar +0.25, the cow +0.15 (`quality` −0.27) — so not the default (README,
    "Stop 54")."""
    contact_band: float = 0.05
    """Height above the support plane (working-sphere radii) where the object meets the floor or table: there a
    point is carved, and a mask-background ray's surface point pushed free, only when ≥ 2 views' masks say so
    (automatic masks are least sure at the contact line; one view missing it cut the bottom off a lying book)."""
    appearance: Literal["auto", "on", "off"] = "auto"
    """Fit a per-view colour transform (exposure and white balance: a gain per channel and view,
    see dvr/appearance.py) between the shared texture field and each photo; the fitted gains are written to
    ``model/appearance.json`` and undone in the texture bake. auto: on when the photos differ in exposure by
    more than ``appearance_spread`` as the pipeline's cameras stage measured it on the SfM points' colours
    (``exposure.json``, pipeline/scene/exposure.py); off without that record (given cameras, or dvr alone)."""
    appearance_spread: float = 0.05
    """With ``appearance`` auto: the exposure spread (the 90th percentile over the photos of their largest
    |log gain| against the average photo; 0.05 ≈ 5 %) above which the per-view appearance is on. Scenes
    without exposure changes measure under 1 %, auto-exposed captures 10–30 %."""
    clipped_level: float = 0.98
    """With ``appearance`` or ``view_shading``: a photo channel at or above this level is over-exposed (clipped),
    and the RGB loss lets the rendered colour be brighter there (:func:`dvr.losses.rgb_loss`), so that a view
    photographed brighter (a gain above 1 puts the render above 1 where the photo clipped) does not pull the
    texture field darker and its gain lower. Above 1: off. (Without them the render never exceeds 1.)"""
    view_shading: bool = False
    """Explain highlights that move with the camera by a small view-dependent residual colour in training
    (:mod:`dvr.shading`: an MLP of the reflected ray direction and the point, L1-pulled to zero), so that the
    diffuse texture field and the geometry do not absorb them; only the diffuse field is kept."""
    hull_gate: bool = True
    """Apply the occupancy loss (mask rays the rendering misses) only where the visual hull agrees the point can
    be occupied: a pixel one view's mask got wrong is outvoted instead of growing a floater."""
    weights: LossWeights = field(default_factory=LossWeights)
    """Loss weights."""
    field: FieldConfig = field(default_factory=FieldConfig)
    """Field representation."""
    checkpoint_every: PositiveInt = 250
    """Steps between checkpoints (resume after a kill continues from the last)."""
    log_every: PositiveInt = 25
    """Steps between log.jsonl lines."""
    preview_every: int = 500
    """Steps between preview renders (0: only at the end)."""
    seed: int = 0
    """Random seed (fixed for reproducible runs)."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu' or 'cuda'."""
    threads: int = 0
    """CPU threads for torch (0: torch's default)."""
    progress: bool = True
    """Show a progress bar."""
