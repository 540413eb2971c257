"""Pairs of similar photos for matching many photos (pipeline/cameras/pairs.py): the coarse match (smoke, bad
input), the batched similarity against the pairwise reference, the neighbours picked, and on rendered photos the
pairs a coarse match picks join the photos taken from nearby, and the cameras stage poses the photos from them."""

import json

import numpy as np
import pytest
import torch

from dvr.cameras import load_cameras
from dvr.data import list_images
from dvr.metrics import pose_errors
from pipeline.cameras.pairs import coarse_matches, neighbour_pairs, similarity
from pipeline.cli import main
from tests.pipeline.cameras.test_ladder_bounds import _centres, _torus_photos


def _sift_like(n: int, rng: np.random.Generator) -> torch.Tensor:
    """Unit vectors with SIFT's non-negative entries."""
    d = rng.exponential(1.0, (n, 128))
    return torch.from_numpy(d / np.linalg.norm(d, axis=1, keepdims=True)).float()


def _seen_again(d: torch.Tensor, rng: np.random.Generator, noise: float = 0.02) -> torch.Tensor:
    """The same features seen from elsewhere: a little noise, renormalised, in another order."""
    e = d.numpy()[rng.permutation(len(d))] + noise * rng.random((len(d), d.shape[1]))
    return torch.from_numpy(e / np.linalg.norm(e, axis=1, keepdims=True)).float()


def test_coarse_matches_counts_features_seen_again():
    rng = np.random.default_rng(0)
    a = _sift_like(60, rng)
    b = torch.cat([_seen_again(a[:25], rng), _sift_like(35, rng)])
    assert coarse_matches(a, b) == 25
    assert coarse_matches(a, _sift_like(60, rng)) <= 1  # unrelated photos: the ratio test stops chance neighbours
    assert coarse_matches(a, a[:1]) == 0 and coarse_matches(a[:0], b) == 0


def test_coarse_matches_refuses_mismatched_descriptors():
    with pytest.raises(ValueError, match="descriptors must be"):
        coarse_matches(torch.zeros(4, 128), torch.zeros(4, 64))
    with pytest.raises(ValueError, match="descriptors must be"):
        coarse_matches(torch.zeros(128), torch.zeros(4, 128))


def test_similarity_is_the_pairwise_coarse_match():
    """Photos of 60, 40, 1, 0 and 60 features, some sharing features: the batched similarity (zero-padded) holds
    :func:`coarse_matches` of every pair, from the earlier photo's side, mirrored; 0 on the diagonal and for a photo
    of fewer than two features (no second neighbour for the ratio test)."""
    rng = np.random.default_rng(1)
    base = _sift_like(60, rng)
    photos = [base, torch.cat([_seen_again(base[:20], rng), _sift_like(20, rng)]), base[:1], base[:0],
              torch.cat([_seen_again(base[30:], rng), _seen_again(base[:30], rng, 0.2)])]
    score = similarity(photos)
    assert score.shape == (5, 5) and (score == score.T).all() and (np.diag(score) == 0).all()
    for i in range(5):
        for j in range(i + 1, 5):
            assert score[i, j] == coarse_matches(photos[i], photos[j]), (i, j)
    assert score[0, 1] == 20 and score[0, 4] >= 30


def test_neighbour_pairs_join_each_photo_with_its_best():
    score = np.array([[0, 9, 1, 0],
                      [9, 0, 5, 2],
                      [1, 5, 0, 0],
                      [0, 2, 0, 0]])
    assert neighbour_pairs(score, 1) == [(0, 1), (1, 2), (1, 3)]
    assert neighbour_pairs(score, 2) == [(0, 1), (0, 2), (1, 2), (1, 3)]  # 3's second best scores 0: left out
    with pytest.raises(ValueError, match="square"):
        neighbour_pairs(score[:3], 2)
    with pytest.raises(ValueError, match="at least 1"):
        neighbour_pairs(score, 0)


def test_the_cameras_stage_poses_photos_from_similar_pairs(tmp_path, capsys):
    """16 photos of the torus in two rings, each matched with its 4 most similar photos only: every pair matched
    joins photos taken less than 70° apart, and the model poses all 16 at their true poses."""
    images = _torus_photos(tmp_path, 16)
    ws = tmp_path / "ws"
    assert main(["cameras", str(ws), "--images", str(images), "--cameras.matching", "similar",
                 "--cameras.pair-neighbours", "4", "--cameras.no-board"]) == 0
    capsys.readouterr()
    stamp = json.loads((ws / ".stages" / "cameras.json").read_text())
    assert stamp["registered"] == 16, stamp["rungs"]
    gt = load_cameras(tmp_path / "syn" / "cameras.npz")
    axes = {f"{i:06d}.png": gt.R[i][2] for i in range(16)}  # the viewing directions
    pairs = [line.split() for line in (ws / "sfm" / "ladder" / "matches-f8192-h0.8-pairs.txt").read_text().splitlines()]
    assert 16 * 4 / 2 <= len(pairs) <= 16 * 4, len(pairs)
    angles = [np.degrees(np.arccos(np.clip(axes[a] @ axes[b], -1, 1))) for a, b in pairs]
    assert max(angles) < 70, sorted(angles)[-5:]
    est = load_cameras(ws / "cameras.npz")
    idx = [int(p.stem) for p in list_images(ws / "images")]
    err = pose_errors(_centres(est), est.R, _centres(gt)[idx], gt.R[idx])
    assert err["center_err_rel_max"] < 0.02 and err["rot_err_deg_max"] < 1.0, err
