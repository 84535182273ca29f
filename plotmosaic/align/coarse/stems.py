"""The stem generator: stem maps of the two levelled clouds matched as point patterns (stemmap.py)."""

from __future__ import annotations

import numpy as np

from plotmosaic.align import stemmap
from plotmosaic.align.coarse.clouds import CoarseCloud, hypothesis_transform, unlevelled
from plotmosaic.config.coarse import CoarseConfig


def stem_starts(
    src: CoarseCloud, tgt: CoarseCloud, pairs, config: CoarseConfig, rng: np.random.Generator
) -> list[tuple]:
    """(local 4x4, hypothesis dict) from stem-map matches per vertical pair."""
    out = []
    for vs, vt in pairs:
        ls, lt = src.level(vs, config), tgt.level(vt, config)
        ms, mt = ls.stems(config), lt.stems(config)
        found = stemmap.match_stem_maps(ms, mt, config, rng)
        if not found:
            continue
        ground_tree = lt.ground_tree(config)
        for yaw, t_xy, n in found:
            h = {"yaw": yaw, "t_xy": t_xy, "centre": np.zeros(2)}
            T = unlevelled(hypothesis_transform(h, ls, lt, ground_tree, config), ls, lt)
            out.append(
                (
                    T,
                    {
                        "generator": "stems",
                        "vertical": f"{vs.name}/{vt.name}",
                        "votes": n,
                        "yaw": yaw,
                        "stems": [len(ms.xy), len(mt.xy)],
                    },
                )
            )
    return out
