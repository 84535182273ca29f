"""The pose judge: one verification that every pairwise result goes through (coarse, --init, --no-coarse).

A pose is scored by a residual profile: the share of sample points within several distances
(2-25 cm at the delta0 spacing, stretched for sparse clouds) of the other cloud, on non-flat points
(stems, branches, crowns: flat ground fits anywhere) and on all points, in both directions.
The pose must beat every *distinct* rival (other hypotheses of the global search, the start as
handed over), each refined by a short ICP and profiled the same way: the confidence comes from the
relative margin at the finest scale (`fine_margin`), where a right pose stands out; the wide scales
gather points by chance in a forest and rank wrong rivals close to a right pose. A pose must also be
the sharpest of its own basin: starts a few degrees / decimetres around it, refined the same way, must
not end sharper (`basin`): a near miss (a pose the final ICP left 1-4 deg off, inside the distinct radius
of the truth) has no distinct rival at the truth when the search missed it, but its neighbours reach it.
Every transform here maps source-local to target-local coordinates.

profile.py: samples and residual profiles; rivals.py: rivals and basin starts refined; verdict.py: the
verdict and the stored-pose check.
"""

from plotmosaic.align.judge.profile import (
    agreement,
    centre,
    confidence,
    distinct,
    fine_margin,
    fine_share,
    near,
    profile,
    same,
    separation,
    sharpness,
)
from plotmosaic.align.judge.rivals import basin, neighbours, refine, sharper_neighbours
from plotmosaic.align.judge.verdict import (
    Candidate,
    StoredVerdict,
    Verdict,
    judge,
    second_look,
    verify_stored,
)

__all__ = [
    "Candidate",
    "StoredVerdict",
    "Verdict",
    "agreement",
    "basin",
    "centre",
    "confidence",
    "distinct",
    "fine_margin",
    "fine_share",
    "judge",
    "near",
    "neighbours",
    "profile",
    "refine",
    "same",
    "second_look",
    "separation",
    "sharper_neighbours",
    "sharpness",
    "verify_stored",
]
