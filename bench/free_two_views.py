"""A probe (no option of the pipeline): training pushes free only the points that at least two views' masks carve
(:func:`dvr.hull.outside_hull` with ``min_views`` 2), while the initial hull and the carving term follow the run's
``train.carve_min_views`` (stop 51 measured this with 1, each mask alone; since stop 52 the default is 2, so at the
defaults this probe makes the whole sphere's rule two-view); then any of the bench's one-off runners with its own
arguments:

    python bench/free_two_views.py gt_arm cow
    python bench/free_two_views.py pair cow --arm ""
    python bench/free_two_views.py dtu_arm

README, "one photo's mask carving alone": what the two-view rule over the whole sphere (``--train.contact-band 3``,
which also changes the hull and the carving) does, against this.
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dvr import trainer  # noqa: E402
from dvr.hull import outside_hull  # noqa: E402

RUNNERS = ("gt_arm", "pair", "dtu_arm")


def freespace_points_two_views(push_free):
    """``Trainer.freespace_points`` keeping only the points the masks carve with the run's rules
    (:func:`dvr.trainer.carve_rules`: support plane, contact band, sparse views, sure background) and ≥ 2 views."""

    def points(self, batch):
        pts = push_free(self, batch)
        if pts.shape[0] == 0:
            return pts
        rules = {**trainer.carve_rules(self.cfg, self.data, self.near), "min_views": 2}
        return pts[outside_hull(pts, self.data.P, self.data.masks, **rules)]

    return points


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in RUNNERS:
        sys.exit(f"usage: python bench/free_two_views.py {{{','.join(RUNNERS)}}} ARGS...")
    runner = sys.argv.pop(1)
    trainer.Trainer.freespace_points = freespace_points_two_views(trainer.Trainer.freespace_points)
    module = __import__(f"bench.{runner}", fromlist=["main"])
    module.main()


if __name__ == "__main__":
    main()
