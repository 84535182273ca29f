"""The floors a pose must clear to be returned: fitness, overlap, RMSE and the judge's figures;
below any of them the pair is refused (RegistrationFailed, exit 3), never returned silently."""

from __future__ import annotations

import numpy as np

from plotmosaic.align.result import PairResult
from plotmosaic.config.align import AlignConfig
from plotmosaic.config.judge import JudgeConfig
from plotmosaic.errors import RegistrationFailed


def blunt_fit(sharp: float | None, confidence: float | None, jc: JudgeConfig) -> str | None:
    """Why a pose fits too bluntly to be accepted, or None. Sharp (>= min_sharpness): fine. Between
    blunt_min_sharpness and min_sharpness (noisy sensors, e.g. MLS onto a drone cloud): only a clear
    winner over every distinct rival. Below: chance. Results cached before sharpness: no figure."""
    if sharp is None or sharp >= jc.min_sharpness:
        return None
    conf = -1.0 if confidence is None else confidence
    if sharp >= jc.blunt_min_sharpness:
        if conf >= jc.blunt_min_confidence:
            return None
        return (
            f"blunt fit: sharpness {sharp:.3f} < {jc.min_sharpness} and confidence {conf:.2f} <"
            f" {jc.blunt_min_confidence} (a blunt fit must beat every distinct rival clearly)"
        )
    return (
        f"blunt fit: sharpness {sharp:.3f} < {jc.blunt_min_sharpness} (points come close"
        " to the other cloud only by chance at this pose)"
    )


def check_quality(result: PairResult, config: AlignConfig, local: bool = False) -> None:
    """Refuse a transform the figures do not support (exit 3), never return it silently.

    `local`: the pose came from a start (--no-coarse or --init), which the message names when a rival wins.
    """
    problems = []
    if not np.isfinite(result.transform).all():
        problems.append("transform is not finite")
    # either way: a pair's fit does not depend on which scan is the source, and the smaller view of a
    # thin pair shares less than a tenth of itself at the right pose
    fitness = max(result.fitness, result.fitness_reverse or 0.0)
    if fitness < config.min_fitness:
        problems.append(f"fitness {fitness:.3f} < {config.min_fitness} (either way)")
    if result.overlap < config.min_overlap:
        problems.append(f"overlap {result.overlap:.3f} < {config.min_overlap}")
    if not result.inlier_rmse <= config.max_inlier_rmse:
        problems.append(f"inlier RMSE {result.inlier_rmse:.3f} m > {config.max_inlier_rmse} m")
    j = result.judge
    if j is not None:
        if j["score"] < config.judge.min_score:
            problems.append(
                f"judge score {j['score']:.3f} < {config.judge.min_score} (the clouds hardly fit anywhere)"
            )
        blunt = blunt_fit(j.get("sharpness"), result.confidence, config.judge)
        if blunt:
            problems.append(blunt)
        if (
            j["margin"] <= 0
        ):  # also with min_confidence 0 (register-plot): this pose is not the best one found
            hint = ": rerun without --no-coarse" if local and not config.coarse.enabled else ""
            problems.append(
                f"a distinct pose fits as well or better (judge score {j['rival_score']:.3f}"
                f" against {j['score']:.3f}, from {j['rival_source']}){hint}"
            )
        elif result.confidence is not None and result.confidence < config.min_confidence:
            fine = ""
            if "fine_share" in j:  # results cached before the fine margin lack it
                fine = (
                    f"; share within {j['profile']['scales'][0]:.2f} m {j['fine_share']:.3f},"
                    f" rival {j['fine_rival_share']:.3f} from {j.get('fine_rival_source')}"
                )
            problems.append(
                f"ambiguous: a distinct pose fits almost as well at the finest scale (confidence"
                f" {result.confidence:.2f} < {config.min_confidence}{fine}; judge score"
                f" {j['score']:.3f}, rival {j['rival_score']:.3f})"
            )
    if problems:
        err = RegistrationFailed(
            "pair cannot be registered: "
            + "; ".join(problems)
            + f" (fitness {result.fitness:.3f}, overlap {result.overlap:.3f}, inlier RMSE {result.inlier_rmse:.3f} m"
            f" at {config.quality_distance} m)"
        )
        err.result = result
        raise err
