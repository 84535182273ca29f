"""The merged cloud as COPC (cloud-optimised LAZ: an octree of LAZ chunks), written by copclib.

The points are merge's output, exactly: `merge` writes them first (into a scratch folder beside
the output), then each is put in one octree node, with the same stored integers, scale, offset, CRS
and point format (extra dimensions such as the simulator's `label` are left out: the writer does
not carry their names). The octree is a cube of GRID << shift integers over the cloud; a node
covers GRID^3 cells and keeps the first point (in merge's order) of each cell its region's
remaining points fill, passing the rest to its 8 children; a region of at most LEAF_POINTS points,
or at 1-integer cells, is one node. COPC's spacing is then the root's cell edge.

Memory is bounded by merge's tile budget (`[merge] tile_memory_mb`, at least LEAF_POINTS points;
and a streamed node's own points, at most GRID^3): a region over it is streamed
block by block (its node's taken cells are a GRID^3 bitmap) with the rest spilled into its
children's files in the scratch folder; a region within it is built in memory. Nodes are written as
they are made (the writer keeps only the hierarchy); a hierarchy page holds PAGE_LEVELS levels.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from plotmosaic.config.merge import MergeConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import atomic_output, temp_folder
from plotmosaic.manifest import Manifest
from plotmosaic.poses import Poses
from plotmosaic.stages.export.plan import Advance, points_progress
from plotmosaic.stages.merge import merge_scans
from plotmosaic.stages.merge.plan import MergeSummary, sidecar_path
from plotmosaic.stages.merge.records import first_in_voxel, take_records
from plotmosaic.stages.merge.tiles import Bucket, scatter, tile_points

GRID_BITS = 7
GRID = 1 << GRID_BITS  # cells along a node's edge
LEAF_POINTS = 100_000  # a region holding at most this many points is one node
PAGE_LEVELS = 4  # octree levels per hierarchy page
STREAM_SHARE = 3  # a streamed block is this share of the budget: picking and spilling copy it often
_CHILD = np.array([4, 2, 1])  # octant label of a child from its index bits (x, y, z)


@dataclass(frozen=True, kw_only=True)
class Cube:
    """The octree's cube in the cloud's stored integers."""

    origin: np.ndarray  # (3,) int64, the low corner
    shift: int  # edge = GRID << shift integers; a depth-d cell is 1 << (shift - d) integers

    @classmethod
    def around(cls, lo: np.ndarray, hi: np.ndarray) -> Cube:
        span = int(np.max(hi - lo)) + 2
        shift = max(0, (-(-span // GRID) - 1).bit_length())
        edge = GRID << shift
        return cls(origin=lo + (hi - lo) // 2 - edge // 2, shift=shift)

    @property
    def edge(self) -> int:
        return GRID << self.shift

    def cells(self, raw: np.ndarray, depth: int) -> np.ndarray:
        """(N, 3) int64 cell indices of records at `depth` (a node's index is cells >> GRID_BITS)."""
        ijk = np.empty((len(raw), 3), dtype=np.int64)
        for axis, name in enumerate("XYZ"):
            ijk[:, axis] = (raw[name].astype(np.int64) - self.origin[axis]) >> (self.shift - depth)
        return ijk


@dataclass(frozen=True, kw_only=True)
class CopcSummary:
    merge: MergeSummary
    out: Path
    points: int
    nodes: int
    depth: int
    spacing: float
    dropped: tuple[str, ...]  # extra dimensions of the merge not carried into the COPC


Key = tuple[int, int, int, int]  # depth, x, y, z


class _Nodes:
    """The COPC writer's side: nodes added as they are made, counted."""

    def __init__(self, writer, copclib, advance: Advance | None):
        self.writer, self.copclib, self.advance = writer, copclib, advance
        self.points = self.count = self.depth = 0
        self.gps = [np.inf, -np.inf]

    def add(self, key: Key, records: np.ndarray) -> None:
        if not len(records):
            return
        page = (key[0] // PAGE_LEVELS) * PAGE_LEVELS
        up = key[0] - page
        page_key = self.copclib.VoxelKey(page, key[1] >> up, key[2] >> up, key[3] >> up)
        data = self.copclib.VectorChar(np.ascontiguousarray(records).view(np.int8))
        self.writer.AddNode(self.copclib.VoxelKey(*key), data, page_key)
        if "gps_time" in records.dtype.names:
            self.gps = [
                min(self.gps[0], records["gps_time"].min()),
                max(self.gps[1], records["gps_time"].max()),
            ]
        self.points += len(records)
        self.count += 1
        self.depth = max(self.depth, key[0])
        if self.advance is not None:
            self.advance(len(records), f"depth {key[0]}")


def _children(cube: Cube, key: Key, records: np.ndarray) -> list[tuple[Key, np.ndarray]]:
    """Records grouped by the child node they fall in (stream order kept within each)."""
    index = cube.cells(records, key[0] + 1) >> GRID_BITS
    labels = (index & 1) @ _CHILD
    out = []
    for label in np.unique(labels):
        rows = np.flatnonzero(labels == label)
        out.append(((key[0] + 1, *(int(v) for v in index[rows[0]])), take_records(records, rows)))
    return out


def _rest(n: int, keep: np.ndarray) -> np.ndarray:
    mask = np.ones(n, dtype=bool)
    mask[keep] = False
    return np.flatnonzero(mask)


def _in_memory(nodes: _Nodes, cube: Cube, key: Key, records: np.ndarray) -> None:
    stack = [(key, records)]
    while stack:
        key, records = stack.pop()
        if len(records) <= LEAF_POINTS or key[0] == cube.shift:
            nodes.add(key, records)
            continue
        keep = first_in_voxel(cube.cells(records, key[0]))
        nodes.add(key, take_records(records, keep))
        stack.extend(_children(cube, key, take_records(records, _rest(len(records), keep))))


def _streamed(
    nodes: _Nodes, cube: Cube, key: Key, blocks: Iterable[np.ndarray], folder: Path, budget: int
) -> None:
    """A region over the memory budget: its node's points picked block by block, the rest spilled
    into one file per child, then each child built the same way."""
    taken = np.zeros(GRID**3, dtype=bool)
    kept: list[np.ndarray] = []
    spill: dict[int, Bucket] = {}

    def bucket(label) -> Bucket:
        label = int(label)
        if label not in spill:
            spill[label] = Bucket(
                folder / f"{key[0] + 1}-{'-'.join(map(str, key[1:]))}-{label}.bin"
            )
        return spill[label]

    dtype = None
    for raw in blocks:
        dtype = raw.dtype
        cells = cube.cells(raw, key[0])
        first = first_in_voxel(cells)
        local = cells[first] & (GRID - 1)
        flat = (local[:, 0] << (2 * GRID_BITS)) | (local[:, 1] << GRID_BITS) | local[:, 2]
        new = ~taken[flat]
        taken[flat[new]] = True
        kept.append(take_records(raw, first[new]))
        rest = take_records(raw, _rest(len(raw), first[new]))
        if len(rest):
            index = cube.cells(rest, key[0] + 1) >> GRID_BITS
            scatter(rest, index, (index & 1) @ _CHILD, bucket)
    nodes.add(key, np.concatenate(kept) if kept else np.empty(0))
    for label in sorted(spill):
        b = spill[label]
        child = (key[0] + 1, *(2 * k + ((label >> s) & 1) for k, s in zip(key[1:], (2, 1, 0))))
        blocks = _file_blocks(b.path, dtype, budget // STREAM_SHARE)
        _region(nodes, cube, child, b.count, blocks, folder, budget)
        b.path.unlink()


def _file_blocks(path: Path, dtype: np.dtype, count: int) -> Iterator[np.ndarray]:
    with open(path, "rb") as f:
        while len(raw := np.fromfile(f, dtype=dtype, count=count)):
            yield raw


def _region(nodes, cube, key: Key, count: int, blocks, folder: Path, budget: int) -> None:
    if count <= budget or key[0] == cube.shift:
        _in_memory(nodes, cube, key, np.concatenate(list(blocks)))
    else:
        _streamed(nodes, cube, key, blocks, folder, budget)


def base_records(raw: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """The records without their extra bytes (which follow the standard fields)."""
    if raw.dtype.itemsize == dtype.itemsize:
        return raw
    rows = np.ascontiguousarray(raw).view(np.uint8).reshape(len(raw), raw.dtype.itemsize)
    return np.ascontiguousarray(rows[:, : dtype.itemsize]).reshape(-1).view(dtype)


def _config(copclib, header: laspy.LasHeader, cube: Cube, wkt: str | None):
    """The COPC header: merge's point format, scale, offset and bounds; the octree's cube."""
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    if not np.allclose(scales, scales[0]):
        raise InputError("COPC needs one scale on every axis")  # merge always writes one
    cfg = copclib.CopcConfigWriter(
        int(header.point_format.id),
        copclib.Vector3(*map(float, scales)),
        copclib.Vector3(*map(float, offsets)),
        wkt or "",
    )
    cfg.las_header.min = copclib.Vector3(*map(float, header.mins))
    cfg.las_header.max = copclib.Vector3(*map(float, header.maxs))
    cfg.las_header.global_encoding = (16 if wkt else 0) | (header.global_encoding.value & 1)
    centre = offsets + scales * (cube.origin + cube.edge / 2)
    info = cfg.copc_info
    info.center_x, info.center_y, info.center_z = map(float, centre)
    info.halfsize = float(scales[0] * cube.edge / 2)
    info.spacing = float(scales[0] * (1 << cube.shift))
    return cfg


def _octree(merged: Path, tmp: Path, folder: Path, summary: MergeSummary, budget_mb: int, advance):
    """The merged file's points written into the COPC file `tmp`."""
    import copclib  # deferred: its C++ library loads only when a COPC file is written

    with laspy.open(merged) as reader:
        header = reader.header
        base = laspy.PointFormat(header.point_format.id).dtype()
        lo = np.rint((header.mins - header.offsets) / header.scales).astype(np.int64)
        hi = np.rint((header.maxs - header.offsets) / header.scales).astype(np.int64)
        cube = Cube.around(lo, hi)
        # a region of LEAF_POINTS is one node, written whole: the budget is never below it
        budget = max(LEAF_POINTS, tile_points(MergeConfig(tile_memory_mb=budget_mb), base, 1))
        writer = copclib.FileWriter(str(tmp), _config(copclib, header, cube, summary.crs))
        nodes = _Nodes(writer, copclib, advance)
        blocks = (
            base_records(c.array, base) for c in reader.chunk_iterator(budget // STREAM_SHARE)
        )
        _region(nodes, cube, (0, 0, 0, 0), int(header.point_count), blocks, folder, budget)
        if np.isfinite(nodes.gps[0]):
            gps = writer.copc_config.copc_extents.gps_time
            gps.minimum, gps.maximum = map(float, nodes.gps)
        writer.Close()
        dropped = tuple(header.point_format.extra_dimension_names)
    return nodes, cube, dropped, float(header.scales[0])


def write_copc(
    manifest: Manifest,
    poses: Poses,
    out: Path,
    config: MergeConfig,
    poses_path: Path | None = None,
    progress: bool = True,
) -> CopcSummary:
    """Merge (as `merge` does, with its options) and write the result as COPC at `out`, with a
    sidecar `<out>.json` (the merge's source table and counts); both atomically."""
    with temp_folder(out, ".copc") as folder:
        merged = folder / "merged.las"
        single = config.model_copy(update={"tiles": False})
        summary = merge_scans(manifest, poses, merged, single, progress, poses_path)
        with (
            atomic_output(out, force=True) as tmp,
            points_progress(progress, "copc", summary.points_out) as advance,
        ):
            nodes, cube, dropped, scale = _octree(
                merged, tmp, folder, summary, config.tile_memory_mb, advance
            )
        if nodes.points != summary.points_out:
            raise RuntimeError(f"COPC holds {nodes.points} points of {summary.points_out} merged")
    result = CopcSummary(
        merge=summary,
        out=out,
        points=nodes.points,
        nodes=nodes.count,
        depth=nodes.depth,
        spacing=scale * (1 << cube.shift),
        dropped=dropped,
    )
    data = {
        "poses": str(poses_path) if poses_path else None,
        "frame": poses.frame,
        **summary.to_dict(),
        "out": str(out),
        "copc": {"nodes": result.nodes, "depth": result.depth, "spacing": result.spacing},
        "dropped_fields": list(dropped),
    }
    with atomic_output(sidecar_path(out), force=True) as tmp_json:
        tmp_json.write_text(json.dumps(data, indent=1))
    return result
