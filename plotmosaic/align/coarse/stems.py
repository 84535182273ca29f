"""The stem generator: stem maps of the two levelled clouds matched as point patterns (stemmap.py)."""

from __future__ import annotations

import numpy as np

from plotmosaic.align import stemmap
from plotmosaic.align.coarse.clouds import Levels, hypothesis_transform, unlevelled
from plotmosaic.align.coarse.hypothesis import Start
from plotmosaic.config.coarse import CoarseConfig


def stem_starts(
    src: Levels, tgt: Levels, pairs, config: CoarseConfig, rng: np.random.Generator
) -> list[Start]:
    """Starts from stem-map matches per vertical pair."""
    out = []
    for vs, vt in pairs:
        ls, lt = src.level(vs, config), tgt.level(vt, config)
        ms, mt = src.stems(vs, config), tgt.stems(vt, config)
        found = stemmap.match_stem_maps(ms, mt, config, rng)
        if not found:
            continue
        ground_tree = tgt.ground_tree(vt, config)
        for yaw, t_xy, n in found:
            A = hypothesis_transform(
                ls, lt, ground_tree, config, yaw=yaw, t_xy=t_xy, centre=np.zeros(2)
            )
            out.append(
                Start(
                    T=unlevelled(A, ls, lt),
                    generator="stems",
                    vertical=f"{vs.name}/{vt.name}",
                    votes=n,
                    yaw=yaw,
                )
            )
    return out
