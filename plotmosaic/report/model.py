"""What the report pages pass between their steps: the run's input, each plot's view, figures."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.report.als_fit import AlsFit
from plotmosaic.report.slice import Ground, Stem, ring_spread


@dataclass(frozen=True)
class Stage:
    """One row of the page's time table (wall seconds; None when the run did not record it)."""

    name: str
    seconds: float | None
    note: str = ""


@dataclass(frozen=True, kw_only=True)
class Figure:
    """A picture on the page: its plot ('' for the page's own), caption and how to read it."""

    plot: str
    caption: str
    png: Path
    read: str = ""


@dataclass(frozen=True, kw_only=True)
class PlotView:
    """What the report computes for one plot (a set of scans in one frame)."""

    plot: str
    scans: tuple[str, ...]
    ground: Ground | None = None
    slices: dict[str, np.ndarray] = field(default_factory=dict)
    stems: list[Stem] = field(default_factory=list)
    thinned: dict[str, np.ndarray] = field(default_factory=dict)
    scan_minima: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    stations: dict[str, np.ndarray] = field(default_factory=dict)  # each scanner's position
    edges: list[dict] = field(default_factory=list)  # per kept edge: distances and their figures
    medians: dict[str, float] = field(default_factory=dict)
    als: AlsFit | None = None

    @property
    def spread(self) -> float:
        return ring_spread(self.stems)


@dataclass(frozen=True, kw_only=True)
class ReportInput:
    """Everything build_report needs, from whichever run made the poses."""

    title: str
    out: Path
    graph: nx.Graph
    poses: dict[str, np.ndarray]
    paths: dict[str, Path]
    plots: dict[str, list[str]]  # plot id -> scan ids
    reader: Callable[[Path], np.ndarray]
    stages: tuple[Stage, ...] = ()
    unplaced: tuple[str, ...] = ()
    failed: tuple[dict, ...] = ()
    facts: tuple[str, ...] = ()  # lines for the summary (manifest, frame, ...)
    blocks: tuple[tuple[str, str], ...] = ()  # (heading, HTML) sections right after the summary
    figures: tuple[Figure, ...] = ()  # pictures the caller drew, first among the pictures
    tables_md: tuple[tuple[str, list[str]], ...] = ()  # report.md tables repeated on the page
    als_xyz: np.ndarray | None = None  # the ALS around the scans: map background, fit, 3D layer
    # plot id -> (link to the report that measured its cloud-to-cloud distances, why): plots a
    # later solve moved as one piece, whose distances are that report's
    judged_in: dict[str, tuple[str, str]] = field(default_factory=dict)
    min_confidence: float = field(default_factory=lambda: PoseGraphConfig().sure_edge_confidence)
    bundle: dict | None = None  # residual summary of the kept edges
    overview: bool = False  # a top and side view of each plot's placed scans
