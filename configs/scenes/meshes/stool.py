"""Writes stool.obj beside this file: a 0.9 × 0.9 × 0.15 seat on four 0.12 × 0.12 legs 0.85 high, as ONE closed
surface (no faces inside the solid: the legs' tops and the seat's underside where they join are not surface, and a
ground truth that kept them would count them as missed by every reconstruction).

    python configs/scenes/meshes/stool.py

The solid is a union of boxes on one grid of their edges: every face between a filled cell and an empty one (or
the outside) is a quad of the boundary, so the surface is closed and has no T-junctions.
"""
from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

SEAT = ((-0.45, 0.45), (-0.45, 0.45), (0.85, 1.0))
LEGS = [((x0, x0 + 0.12), (y0, y0 + 0.12), (0.0, 0.85)) for x0 in (-0.42, 0.3) for y0 in (-0.42, 0.3)]


def boxes_surface(boxes) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of the boundary of the union of axis-aligned ``boxes`` ((lo, hi) per axis each),
    outward-facing."""
    edges = [sorted({v for b in boxes for v in b[a]}) for a in range(3)]
    shape = tuple(len(e) - 1 for e in edges)
    centre = [0.5 * (np.array(e[1:]) + np.array(e[:-1])) for e in edges]
    filled = np.zeros(shape, bool)
    for idx in itertools.product(*(range(n) for n in shape)):
        p = [centre[a][idx[a]] for a in range(3)]
        filled[idx] = any(all(b[a][0] < p[a] < b[a][1] for a in range(3)) for b in boxes)
    verts: dict[tuple[int, int, int], int] = {}
    tris = []

    def vid(ijk):
        return verts.setdefault(ijk, len(verts))

    for idx in zip(*np.nonzero(filled)):
        for axis, step in itertools.product(range(3), (-1, 1)):
            nb = list(idx)
            nb[axis] += step
            if 0 <= nb[axis] < shape[axis] and filled[tuple(nb)]:
                continue
            u, v = (axis + 1) % 3, (axis + 2) % 3  # (axis, u, v) cyclic: u × v points along +axis
            plane = idx[axis] + (step > 0)
            corners = []
            for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                c = [0, 0, 0]
                c[axis], c[u], c[v] = plane, idx[u] + du, idx[v] + dv
                corners.append(vid(tuple(c)))
            # counter-clockwise in (u, v): the normal is +axis; reversed for the face looking down the axis
            if step < 0:
                corners = corners[::-1]
            tris += [corners[:3], [corners[0], corners[2], corners[3]]]
    xyz = np.array([[edges[a][k[a]] for a in range(3)] for k in verts], float)
    return xyz, np.array(tris, np.int64)


def main() -> None:
    import trimesh

    v, f = boxes_surface([SEAT, *LEGS])
    mesh = trimesh.Trimesh(v, f, process=True)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0, "stool: not a closed solid"
    out = Path(__file__).with_suffix(".obj")
    mesh.export(out)
    print(f"stool: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, volume {mesh.volume:.4f} → {out}")


if __name__ == "__main__":
    main()
