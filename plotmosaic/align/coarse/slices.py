"""The slice generator: fine height-slice occupancy correlated over heading x shift (align/slices.py:
sparse ground views the 1 m rasters miss), run only when the first vertical pair has not settled."""

from __future__ import annotations

from plotmosaic.align import slices
from plotmosaic.align.coarse.clouds import Levels, hypothesis_transform, unlevelled
from plotmosaic.align.coarse.hypothesis import Start
from plotmosaic.config.coarse import CoarseConfig


def slice_starts(src: Levels, tgt: Levels, pairs, config: CoarseConfig) -> list[Start]:
    """Starts of the height-slice occupancy search per vertical pair."""
    out = []
    for vs, vt in pairs:
        ls, lt = src.level(vs, config), tgt.level(vt, config)
        ground_tree = tgt.ground_tree(vt, config)
        for h in slices.slice_search(ls.points, ls.hag, lt.points, lt.hag, config):
            A = hypothesis_transform(
                ls, lt, ground_tree, config, yaw=h.yaw, t_xy=h.t_xy, centre=h.centre
            )
            out.append(
                Start(
                    T=unlevelled(A, ls, lt),
                    generator="slices",
                    vertical=f"{vs.name}/{vt.name}",
                    slice_score=h.score,
                    yaw=h.yaw,
                    overlap=h.overlap,
                )
            )
    return out
