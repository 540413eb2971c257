"""Options of the ``texture`` stage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from dvr.options import PositiveInt


@dataclass
class TextureConfig:
    """UV texturing from the photos (stage ``texture``)."""

    size: PositiveInt = 2048
    """Largest texture side in texels (the atlas is sized by ``texel_density`` up to this)."""
    texel_density: float = 1.5
    """Texels per unit length on the object per photo pixel, where the photos see it best: the texture holds
    what the photos hold (400×300 photos need no 2048² atlas; 1.0 cost 0.16 dB held-out PSNR against 1.5 on the
    book scene, 2048² gained 0.1 dB in 7× the time); 0: the density that fills a ``size`` square."""
    padding: int = 4
    """Texels between charts in the atlas."""
    gutter: int = 8
    """Texels of colour dilated around every chart."""
    angle_power: float = 2.0
    """Sharpness of the view weighting by the cosine between normal and viewing direction (weight cos^this). Held
    out, against 4 (stop 31, same mapping and training): power 2 DTU 18.51 → 18.72 dB (its roofs look brighter from
    low views, and a flatter weighting averages that), the cow with GT cameras −0.03 (`balanced` 29.09 → 29.05);
    power 1 DTU 18.80, the jar from photos +0.16, the cow from photos −0.02, with GT cameras −0.06 (`balanced`
    28.99: on exact geometry the frontal views' sharper pixels count for more)."""
    min_cos: float = 0.1
    """Views seeing a surface more grazing than this cosine are ignored."""
    depth_tolerance: float = 0.01
    """Visibility test: |texel depth − rendered depth| below this (normalized units) counts as visible."""
    edge_px: int = 1
    """Photo pixels within this distance of a depth discontinuity or silhouette count as edge pixels."""
    edge_weight: float = 0.02
    """Weight factor of samples that use an edge pixel (they blend foreground and background in real photos)."""
    silhouette_px: int = 0
    """Photo pixels within this distance of the mesh's silhouette against the background (where the mesh is a
    little too large they show the background: the fringe) count only for texels nothing else sees, and those
    texels then take the fallback colour (texture field, else the nearest seen texel). 0: off, they count as edge
    pixels. 1 removes the fringe on a 3 % too large mesh but costs 0.7 dB at one held-out view of the exact-geometry
    cow (its silhouette pixels are right there), so it is off by default until measured on real captures."""
    edge_fallback_only: bool = True
    """Samples that use an edge pixel count only for texels that no clean sample sees (else they blend in at
    ``edge_weight``): background colour beside a silhouette does not reach a texel another view sees cleanly."""
    outlier_threshold: float = 0.1
    """Photo-consistency: a second blending pass weights every sample by 1 / (1 + (d / this)²), d its RMS colour
    distance to the texel's robust colour (per channel, the mean without the largest and smallest sample), so a
    highlight, shadow or occluder one view alone sees does not reach the texture; 0: off."""
    outlier_reject: float = 3.0
    """Samples farther than this × ``outlier_threshold`` from the robust colour are dropped where 3 or more views
    see the texel."""
    clipped_level: float = 0.98
    """With per-view gains fitted in training (``model/appearance.json``): a photo pixel with a channel at or above
    this level is over-exposed (clipped). It shows only that the surface is at least that bright, and undoing the
    view's gain turns it into too dark a colour. Above 1: off. (Without the gains the views differ by exposure
    anyway; keeping clipped pixels out would only prefer the darker views.)"""
    clipped_weight: float = 0.01
    """Weight factor of samples on over-exposed pixels (and their neighbours): they colour a texel where no view
    sees it unclipped."""
    sharpness_power: float = 0.5
    """Prefer sharp views: weights × (1 + c / ``sharpness_floor``)^this, c the photo's local contrast per unit
    length on the surface (blurred Sobel magnitude × focal / distance; lower in a defocused or shaken view); 0: off."""
    sharpness_floor: float = 2.0
    """Contrast (grey levels of 1 per normalized unit) below which a view counts as flat: weak texture barely
    changes the weights."""
    view_selection: bool = False
    """Discrete view selection (:mod:`pipeline.texture.view_select`): one photo per face, the sharpest, most frontal,
    closest photo-consistent one, under a Potts smoothness so charts come from few views, blended with its neighbours'
    views at chart borders; the other views keep ``selection_floor`` of their weight. Off: every view blends by
    weight."""
    selection_smoothness: float = 1.0
    """Potts weight: cost of a label change between two adjacent faces, in units of −log of the data term's ratio
    to the face's best view (1: a view e times weaker is taken to spare one border edge)."""
    selection_sharpness: float = 2.0
    """Sharpness power of the selection's data term (as ``sharpness_power`` for the blend; the selection's choice
    between two views rests on it). Needs ``sharpness_power`` > 0 (the sharpness maps)."""
    selection_rings: int = 2
    """Rings of neighbouring faces over which the views of two charts blend at their border (0: hard seams)."""
    selection_floor: float = 0.02
    """Weight factor of the views a face did not select (they colour texels the chosen view does not see)."""
    seam_levelling: bool = True
    """Global seam levelling: per view an RGB offset per mesh vertex, solved in least squares (scipy sparse) so that
    overlapping views agree, added to the view's samples before blending (exposure, white balance and lighting
    steps between views do not become seams)."""
    seam_smoothness: float = 10.0
    """Weight of equal offsets at the two ends of a mesh edge, per sample of data (larger: smoother offsets)."""
    seam_zero_pull: float = 0.01
    """Weight of the pull of every offset towards 0, per sample of data (keeps the problem well posed)."""
    seam_fit_texels: int = 200000
    """Texels (drawn with a fixed seed) the offsets are fitted on; all texels get them."""
    frame: Literal["sfm", "normalized"] = "sfm"
    """Frame of the textured outputs: 'sfm' (that of cameras.npz) or 'normalized'."""
    device: str = "auto"
    """Device of the texture field used for unseen texels."""
