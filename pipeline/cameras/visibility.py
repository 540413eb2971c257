"""Visibility check of an SfM model: a group of photos joined to the others at the wrong side of the object.

An object with the same pattern on two sides (a mouse with the same printed grip on its left and right) lets SIFT
match a photo of one side with photos of the other. Where only a few true matches join a group of photos to the
rest, such false matches can outnumber them, and both COLMAP mappers place the group, consistent in itself, at the
other side: 24 of a phone's photos of such a mouse gave five views 84° from their true place at 0.39 px. The
reprojection error cannot see it, nor can the aim check (the views still look at the object). The points can: the
points the misplaced group alone observes float in front of what the other views observe, or the others' points in
front of the group's.

* :func:`occlusion_conflicts` finds, for each view, the model's points it does not observe that it would see in
  front of a point it does observe (within a few pixels, clearly nearer): a point there would hide the one the view
  observes. A right model has few, in few views; a view with many is conflicted (:func:`conflicted_views`). Of 24
  photos of the mouse, the misjoined model has three conflicted views (8–9 conflicts at points three views observe
  or more), and mapped from slightly different photos (the same, upsampled to 12 MP) two (42 and 53 at points two
  views observe); the bench's right models at most 6 and 19.
* :func:`misjoined_group` finds the group: the photos split into groups joined by pairs with at least a number of
  matches the model explains (:func:`explained_matches`), the least number that puts most conflicts between groups.
* :func:`unexplained_pairs`: where the conflicts do not show a misjoined group (it lies on the object's surface,
  turned about its axis), a pair of photos with many verified matches that the model does not explain does, and
  :func:`doubts` finds the group those pairs set apart (:func:`split_off`); the stage maps again, and warns.
* :func:`joining_pairs` are the pairs between the group and the others whose matches the model explains: the false
  matches that joined them. Mapped again without them, the group joins the others by the matches it has left, and
  that model is kept when it poses as many photos with at most half the conflicts and fewer at points three or more
  views observe, or, for a group found by its pairs in doubt, under half as many of their matches unexplained
  (:func:`pipeline.cameras.mapping._regrouped`): a right model without those never changes.
"""

from __future__ import annotations

import shutil
import sqlite3
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from pipeline.cameras.pose_sanity import View, model_views
from pipeline.colmaplib import PAIR_ID_BASE, pair_images

MIN_CONFLICTS = 5
"""A view is conflicted with this many conflicts among points at least three views observe (the misjoined mouse's
8–9; the bench's right models at most 4, but for two views of its finely textured torus with 6, at its silhouettes,
whose model mapped again is then not kept)..."""
MIN_CONFLICTS_ANY = 25
"""... or with this many among all the model's points (the misjoined mouse at 12 MP: 42 and 53; the right model of
DTU scan24's 49 photos at most 19, of 20 of them 48, whose model mapped again is then not kept)."""
MIN_UNEXPLAINED = 100
"""A pair of photos with this many verified matches, of which the model explains under half, is one it cannot hold:
the bench's right models leave at most 46 of a pair's matches unexplained (the mouse's 59 photos), the mouse's
misjoined models of 16–30 photos 198–545."""
EXPLAINED_SHARE = 0.5
"""A model explains a pair of photos when at least this share of its verified matches fit the model's poses."""


def occlusion_conflicts(views: list[View], points: np.ndarray, observers: list[np.ndarray], radius_px: float = 4.0,
                        depth_margin: float = 0.1) -> list[tuple[int, int]]:
    """(view, point) for each of the ``points`` (N, 3) a view does not observe (``observers[i]``: the indices of the
    views observing point i) that projects into its photo within ``radius_px`` of a point it observes and nearer
    than that point by more than ``depth_margin`` of its depth: a surface there would hide what the view observes."""
    points = np.asarray(points, float)
    if points.ndim != 2 or points.shape[1] != 3 or len(observers) != len(points):
        raise ValueError(f"points must be (N, 3) with one observer list each, got {points.shape} and "
                         f"{len(observers)} lists")
    seen_by = np.zeros((len(views), len(points)), bool)
    for i, obs in enumerate(observers):
        seen_by[np.asarray(obs, int), i] = True
    out = []
    for v, view in enumerate(views):
        seen = seen_by[v]
        if not seen.any():
            continue
        cam = points @ view.R.T + view.t
        z = cam[:, 2]
        front = z > 1e-9
        uv = np.full((len(points), 2), -1e9)
        uv[front] = (cam[front] @ view.K.T)[:, :2] / z[front, None]
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < view.width) & (uv[:, 1] >= 0) & (uv[:, 1] < view.height)
        tested = np.flatnonzero(inside & ~seen)
        if len(tested) == 0:
            continue
        depth = np.append(z[seen], -np.inf)  # the last: no neighbour
        dist, near = cKDTree(uv[seen]).query(uv[tested], k=min(8, int(seen.sum())), distance_upper_bound=radius_px)
        dist, near = dist.reshape(len(tested), -1), near.reshape(len(tested), -1)
        near = np.where(np.isfinite(dist), near, len(depth) - 1)
        hides = (depth[near] > z[tested, None] * (1 + depth_margin)).any(1)
        out += [(v, int(p)) for p in tested[hides]]
    return out


def misjoined_group(n_views: int, explained: dict[tuple[int, int], int], conflicts: list[tuple[int, int]],
                    observers: list[np.ndarray], conflicted: set[int]) -> set[int] | None:
    """The views a model joined to the others where it should not have, or None: :func:`split_off` by the pairs of
    views each ``conflicted`` view's :func:`occlusion_conflicts` set against each other (the view, and each view
    observing its conflicting point)."""
    if len(conflicted) < 2 or not explained:
        return None
    pairs = [(v, o) for v, p in conflicts if v in conflicted for o in observers[p] if o != v]
    return split_off(n_views, explained, pairs)


def split_off(n_views: int, explained: dict[tuple[int, int], int], pairs: list[tuple[int, int]], share: float = 0.5
              ) -> set[int] | None:
    """The group of views that ``pairs`` of views (at odds in the model) set apart from the others, or None. The
    views split into groups joined by pairs of at least T ``explained`` matches (view pair → matches the model
    explains); T is the least at which ``share`` of ``pairs`` lie between groups. The group is the one, the largest
    apart, that most of the pairs touch, the smaller of two touched as often (None when no T splits them)."""
    if not pairs or not explained:
        return None
    (a, b), w = np.array(list(explained), int).T, np.array(list(explained.values()))

    def labels(threshold: int) -> np.ndarray:
        keep = w >= threshold
        graph = coo_matrix((np.ones(keep.sum()), (a[keep], b[keep])), shape=(n_views, n_views))
        return connected_components(graph, directed=False)[1]

    def apart(lab: np.ndarray) -> bool:
        return sum(lab[v] != lab[o] for v, o in pairs) >= share * len(pairs)

    thresholds = np.unique(np.append(w, w.max() + 1))
    lo, hi = 0, len(thresholds) - 1  # the least threshold that splits: more matches needed, more groups
    if not apart(labels(thresholds[hi])):
        return None
    while lo < hi:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if apart(labels(thresholds[mid])) else (mid + 1, hi)
    lab = labels(thresholds[lo])
    ends = np.bincount([lab[i] for pair in pairs for i in pair], minlength=lab.max() + 1)
    sizes = np.bincount(lab)
    ends[np.argmax(sizes)] = 0  # the largest group is the model the others were joined to
    if not ends.any():
        return None
    group = max(np.flatnonzero(ends), key=lambda g: (ends[g], -sizes[g]))  # of groups touched as often, the smaller
    return {int(v) for v in np.flatnonzero(lab == group)}


def joining_pairs(explained: dict[tuple[int, int], int], totals: dict[tuple[int, int], int], group: set[int]
                  ) -> list[tuple[int, int]]:
    """The pairs between ``group`` and the other views that the model explains (:data:`EXPLAINED_SHARE` of their
    verified matches, ``totals``): the matches that joined the group where it is."""
    return [k for k, e in explained.items() if (k[0] in group) != (k[1] in group) and e >= EXPLAINED_SHARE * totals[k]]


def model_observations(rec, min_track: int = 2) -> tuple[list[View], np.ndarray, list[np.ndarray]]:
    """A pycolmap model's views, its points observed by at least ``min_track`` views, and each point's observing
    views (indices into the views)."""
    views = model_views(rec)
    index = {i: n for n, i in enumerate(rec.reg_image_ids())}
    points, observers = [], []
    for p in rec.points3D.values():
        obs = np.unique([index[e.image_id] for e in p.track.elements if e.image_id in index])
        if len(obs) >= min_track:
            points.append(p.xyz)
            observers.append(obs)
    return views, np.array(points).reshape(-1, 3), observers


def explained_matches(rec, database: Path, max_px: float = 4.0) -> tuple[dict, dict]:
    """Per pair of the model's views (indices as :func:`model_observations`) with verified matches in the COLMAP
    ``database``: (matches within ``max_px`` of the epipolar lines of the model's poses, all verified matches)."""
    order = {rec.image(i).name: n for n, i in enumerate(rec.reg_image_ids())}
    images = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    con = sqlite3.connect(f"file:{database}?mode=ro", uri=True)
    try:
        names = {i: n for i, n in con.execute("select image_id, name from images") if n in order}
        keypoints = {names[i]: np.frombuffer(d, np.float32).reshape(r, c)[:, :2].astype(float)
                     for i, r, c, d in con.execute("select image_id, rows, cols, data from keypoints") if i in names}
        explained, totals = {}, {}
        for pair_id, rows, data in con.execute("select pair_id, rows, data from two_view_geometries where rows > 0"):
            a, b = (names.get(i) for i in pair_images(pair_id))
            if a is None or b is None:
                continue
            m = np.frombuffer(data, np.uint32).reshape(rows, 2)
            err = _epipolar_px(images[a], images[b], rec, keypoints[a][m[:, 0]], keypoints[b][m[:, 1]])
            key = (order[a], order[b])
            explained[key], totals[key] = int((err < max_px).sum()), rows
    finally:
        con.close()
    return explained, totals


def _epipolar_px(im_a, im_b, rec, xy_a: np.ndarray, xy_b: np.ndarray) -> np.ndarray:
    """:func:`sampson_px` of matched pixels of two posed images of a pycolmap model."""
    cam_a, cam_b = rec.camera(im_a.camera_id), rec.camera(im_b.camera_id)
    Ma, Mb = im_a.cam_from_world().matrix(), im_b.cam_from_world().matrix()
    R = Mb[:, :3] @ Ma[:, :3].T
    focal = 0.5 * (cam_a.mean_focal_length() + cam_b.mean_focal_length())
    return sampson_px(cam_a.cam_from_img(xy_a), cam_b.cam_from_img(xy_b), R, Mb[:, 3] - R @ Ma[:, 3], focal)


def sampson_px(xa: np.ndarray, xb: np.ndarray, R: np.ndarray, t: np.ndarray, focal: float) -> np.ndarray:
    """Sampson distance, in pixels of ``focal``, of matches ``xa`` ↔ ``xb`` (N, 2; normalised image coordinates)
    to the epipolar geometry of the relative pose ``R``, ``t`` (a's camera → b's)."""
    if xa.shape != xb.shape or xa.ndim != 2 or xa.shape[1] != 2:
        raise ValueError(f"matches must be two (N, 2) arrays, got {xa.shape} and {xb.shape}")
    pa, pb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    ea, eb = pa @ E.T, pb @ E
    num = np.einsum("ij,ij->i", pb, ea) ** 2
    den = ea[:, 0] ** 2 + ea[:, 1] ** 2 + eb[:, 0] ** 2 + eb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30)) * focal


def conflicted_views(views: list[View], points: np.ndarray, observers: list[np.ndarray]
                     ) -> tuple[list[tuple[int, int]], list[tuple[int, int]], set[int]]:
    """The model's :func:`occlusion_conflicts`; those among the points three or more views observe (points two
    views observe left out, in front and behind: they are the noisier); the views with at least
    :data:`MIN_CONFLICTS` of the latter or :data:`MIN_CONFLICTS_ANY` of the former."""
    conflicts = occlusion_conflicts(views, points, observers)
    long = np.array([i for i, obs in enumerate(observers) if len(obs) >= 3], int)
    among_long = [(v, int(long[p])) for v, p in occlusion_conflicts(views, points[long], [observers[i] for i in long])]
    conflicted = {int(v) for v, n in Counter(v for v, _ in among_long).items() if n >= MIN_CONFLICTS} | \
        {int(v) for v, n in Counter(v for v, _ in conflicts).items() if n >= MIN_CONFLICTS_ANY}
    return conflicts, among_long, conflicted


def misjoined(rec, database: Path) -> tuple[list[str], list[tuple[str, str]], tuple[int, int]] | None:
    """A model's misjoined group (:func:`misjoined_group`) as (its photos, the pairs that join it to the others,
    its conflicts as :func:`count_conflicts`), or None when the model has no such group."""
    views, points, observers = model_observations(rec)
    conflicts, among_long, conflicted = conflicted_views(views, points, observers)
    if len(conflicted) < 2:
        return None
    explained, totals = explained_matches(rec, database)
    group = misjoined_group(len(views), explained, conflicts, observers, conflicted)
    if group is None:
        return None
    cut = joining_pairs(explained, totals, group)
    if not cut:
        return None
    names = sorted(views[v].name for v in group)
    return names, [(views[a].name, views[b].name) for a, b in cut], (len(conflicts), len(among_long))


def count_conflicts(rec) -> tuple[int, int]:
    """The model's conflicts (:func:`conflicted_views`): at all its points, at those three or more views observe."""
    conflicts, among_long, _ = conflicted_views(*model_observations(rec))
    return len(conflicts), len(among_long)


def unexplained(explained: dict[tuple[int, int], int], totals: dict[tuple[int, int], int],
                min_matches: int = MIN_UNEXPLAINED) -> list[tuple[int, int]]:
    """The pairs with at least ``min_matches`` verified matches (``totals``) that the model does not explain
    (``explained``: under :data:`EXPLAINED_SHARE` of them), the most matches first."""
    return sorted((k for k, n in totals.items() if n >= min_matches and explained[k] < EXPLAINED_SHARE * n),
                  key=lambda k: -totals[k])


def unexplained_pairs(rec, database: Path) -> list[tuple[str, str, int, int]]:
    """:func:`unexplained` for a pycolmap model and its COLMAP ``database``: (photo, photo, matches, explained)."""
    return doubts(rec, database)[0]


def doubts(rec, database: Path) -> tuple[list[tuple[str, str, int, int]],
                                         tuple[list[str], list[tuple[str, str]]] | None]:
    """A model's :func:`unexplained_pairs` and the group of photos they set apart from the others (:func:`split_off`,
    every pair between groups) as (its photos, the pairs that join it to the others, :func:`joining_pairs`), or None.
    The strongest matches join each side of the object within itself; the pairs in doubt are true matches across
    the object that false ones outvoted, so the group is the one they all leave (16 of the mouse's photos, mapped
    with guided matching: five photos 56° off, each of them in doubt with one photo of the others)."""
    explained, totals = explained_matches(rec, database)
    names = [rec.image(i).name for i in rec.reg_image_ids()]  # the order of explained_matches' indices
    doubtful = unexplained(explained, totals)
    group = split_off(len(names), explained, doubtful, share=1.0)
    cut = joining_pairs(explained, totals, group) if group else []
    found = (sorted(names[v] for v in group), [(names[a], names[b]) for a, b in cut]) if cut else None
    return [(names[a], names[b], totals[a, b], explained[a, b]) for a, b in doubtful], found


def unexplained_matches(doubtful: list[tuple[str, str, int, int]]) -> int:
    """The verified matches of the pairs in ``doubtful`` (:func:`unexplained_pairs`) that their model leaves
    unexplained."""
    return sum(n - e for _, _, n, e in doubtful)


def database_without(database: Path, pairs: list[tuple[str, str]], out: Path) -> Path:
    """A copy of the COLMAP ``database`` at ``out`` in which the photo ``pairs`` (file names) have no verified
    matches."""
    tmp = out.with_suffix(".tmp")
    shutil.copy(database, tmp)
    con = sqlite3.connect(tmp)
    try:
        ids = {n: i for i, n in con.execute("select image_id, name from images")}
        for a, b in pairs:
            i, j = sorted((ids[a], ids[b]))
            con.execute("update two_view_geometries set rows = 0, data = NULL, config = 1 where pair_id = ?",
                        (i * PAIR_ID_BASE + j,))
        con.commit()
    finally:
        con.close()
    tmp.replace(out)
    return out
