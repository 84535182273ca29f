"""What every export starts from: merge's own sources (scans in manifest order, each with its pose
into the output frame, then the ALS tiles with --include-als) and output CRS, so an export and a
merge of the same inputs agree on what goes where."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from pyproj import CRS

from plotmosaic.config.merge import MergeConfig
from plotmosaic.io.progress import progress_bar, shows_progress
from plotmosaic.manifest import Manifest
from plotmosaic.poses import Poses
from plotmosaic.stages.merge.plan import Source, output_crs, plan_sources

Advance = Callable[[int, str], None]  # progress: (points done, what is being done)


@dataclass(frozen=True, kw_only=True)
class ExportPlan:
    """The sources of a merge of these inputs, decided before anything is written."""

    sources: tuple[Source, ...]
    skipped: tuple[str, ...]  # scans without a pose (--skip-missing)
    ignored: tuple[str, ...]  # posed scans not in the manifest
    frame: str  # "plot" or "crs", as the poses say
    crs: CRS | None
    crs_source: str
    poses_path: Path | None

    @property
    def scans(self) -> tuple[Source, ...]:
        """The posed scans (the ALS tiles, taken as they are, left out)."""
        return tuple(s for s in self.sources if not s.id.startswith("als:"))


def plan_export(
    manifest: Manifest, poses: Poses, config: MergeConfig, poses_path: Path | None = None
) -> ExportPlan:
    sources, skipped, ignored = plan_sources(manifest, poses, config)
    crs, crs_source = output_crs(manifest, poses, sources)
    return ExportPlan(
        sources=tuple(sources),
        skipped=tuple(skipped),
        ignored=tuple(ignored),
        frame=poses.frame,
        crs=crs,
        crs_source=crs_source,
        poses_path=poses_path,
    )


@contextlib.contextmanager
def points_progress(enabled: bool, label: str, total: int) -> Iterator[Advance | None]:
    """A progress bar over `total` points on stderr (none when disabled or not a terminal)."""
    if not shows_progress(enabled):
        yield None
        return
    with progress_bar(True, f"{label} {{task.description}}") as bar:
        task = bar.add_task("", total=total)
        yield lambda n, what: bar.update(task, advance=n, description=what)
