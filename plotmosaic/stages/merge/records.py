"""Point records at the integer level: read chunk by chunk, posed from a file's stored integers to
the output's, and the voxel kernels of thinning (first point in stream order wins)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np

from plotmosaic.config.merge import bbox_limits
from plotmosaic.errors import InputError
from plotmosaic.io.frame import apply_transform, translation
from plotmosaic.io.las import corrupt_data, open_las
from plotmosaic.stages.merge.plan import Source


def voxel_ijk(raw: np.ndarray, step: int) -> np.ndarray:
    """(N, 3) int64 voxel indices of output records (the voxel grid is anchored at the output offset)."""
    ijk = np.empty((len(raw), 3), dtype=np.int64)
    for axis, name in enumerate("XYZ"):
        ijk[:, axis] = np.floor_divide(raw[name], step)
    return ijk


def column_bounds(ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column min and max of an (N, 3) array (column by column: axis=0 reductions are several times slower)."""
    return np.array([ijk[:, k].min() for k in range(3)]), np.array(
        [ijk[:, k].max() for k in range(3)]
    )


def take_records(raw: np.ndarray, index: np.ndarray) -> np.ndarray:
    """raw[index] for a structured point array, as whole rows of bytes (much faster than numpy's
    field-by-field gather of a structured dtype)."""
    raw = np.ascontiguousarray(raw)
    rows = raw.view(np.uint8).reshape(len(raw), raw.dtype.itemsize)
    return np.take(rows, index, axis=0).reshape(-1).view(raw.dtype)


def stable_order(keys: np.ndarray, key_bits: int) -> np.ndarray:
    """argsort(keys, kind="stable") for non-negative int64 keys below 2**key_bits: one plain sort of
    key and index packed together when they fit 63 bits (several times faster), else a stable argsort."""
    index_bits = max(1, int(len(keys) - 1).bit_length())
    if key_bits + index_bits > 63:
        return np.argsort(keys, kind="stable")
    packed = np.sort((keys << index_bits) | np.arange(len(keys), dtype=np.int64))
    return packed & ((1 << index_bits) - 1)


def first_in_voxel(ijk: np.ndarray) -> np.ndarray:
    """Ascending indices of the first row of each distinct voxel (one sort)."""
    if len(ijk) == 0:
        return np.empty(0, dtype=np.int64)
    lo, hi = column_bounds(ijk)
    bits = [int(v).bit_length() for v in hi - lo]
    if sum(bits) <= 62:  # pack the indices into one int64 key (always, but for far-flung outliers)
        key = (ijk[:, 0] - lo[0]) << (bits[1] + bits[2])
        key |= (ijk[:, 1] - lo[1]) << bits[2]
        key |= ijk[:, 2] - lo[2]
        order = stable_order(key, sum(bits))
        ordered = key[order]
        new = np.empty(len(order), dtype=bool)
        new[0], new[1:] = True, ordered[1:] != ordered[:-1]
    else:
        order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))  # stable too
        ordered = ijk[order]
        new = np.empty(len(order), dtype=bool)
        new[0], new[1:] = True, np.any(ordered[1:] != ordered[:-1], axis=1)
    keep = np.zeros(len(order), dtype=bool)
    keep[order[new]] = True  # back in stream order without a second sort
    return np.flatnonzero(keep)


def read_records(path: Path, chunk_size: int) -> Iterator[laspy.ScaleAwarePointRecord]:
    """The file's raw point records chunk by chunk (stored integers, all fields)."""
    with open_las(path) as reader, corrupt_data(path):
        yield from reader.chunk_iterator(chunk_size)


def integer_transform(
    pose: np.ndarray, in_scales, in_offsets, out_scales, out_offsets
) -> np.ndarray:
    """The pose as a map from a file's stored integers to the output's (float64, then rounded):
    unscale the input, apply the pose, rescale for the output, in one 4x4."""
    return (
        np.diag([*(1.0 / np.asarray(out_scales, dtype=np.float64)), 1.0])
        @ translation(-np.asarray(out_offsets, dtype=np.float64))
        @ np.asarray(pose, dtype=np.float64)
        @ translation(in_offsets)
        @ np.diag([*np.asarray(in_scales, dtype=np.float64), 1.0])
    )


def posed_record(
    source: Source,
    chunk: laspy.ScaleAwarePointRecord,
    header: laspy.LasHeader,
    bbox: tuple[float, ...] | None,
    thin: int | None = None,
) -> laspy.ScaleAwarePointRecord:
    """A chunk posed into the output, cropped, with its source id; with `thin` (a voxel edge in output
    integer units), only the first point of each voxel within the chunk.

    Works on the stored integers: one 4x4 maps input integers to output integers, so the
    other fields are copied as they are (the whole record at once when the point formats
    agree, field by field otherwise) instead of being unpacked and packed again.
    """
    M = integer_transform(
        source.transform, chunk.scales, chunk.offsets, header.scales, header.offsets
    )
    raw = chunk.array
    q = np.rint(apply_transform(M, np.column_stack([raw["X"], raw["Y"], raw["Z"]])))
    if len(q) and (q.min() < -(2**31) or q.max() > 2**31 - 1):
        raise InputError(
            f"{source.path}: posed points fall outside the output's coordinate range (is the pose right?)"
        )
    q = q.astype(np.int64)
    index = None
    if bbox is not None:
        lo, hi = bbox_limits(bbox)
        xyz = q * header.scales + header.offsets  # the coordinates as written
        index = np.flatnonzero(np.all((xyz >= lo) & (xyz <= hi), axis=1))
    if thin is not None:
        first = first_in_voxel(np.floor_divide(q if index is None else q[index], thin))
        index = first if index is None else index[first]
    if index is not None:
        raw, q = take_records(raw, index), q[index]
    if raw.dtype == header.point_format.dtype():
        record = laspy.ScaleAwarePointRecord(
            raw, header.point_format, header.scales, header.offsets
        )
    else:  # another point format (LAS 1.2 PF 3, no RGB, other extra bytes): copy the fields by name
        record = laspy.ScaleAwarePointRecord.zeros(len(raw), header=header)
        record.copy_fields_from(laspy.PackedPointRecord(raw, chunk.point_format))
    record.array["X"], record.array["Y"], record.array["Z"] = q[:, 0], q[:, 1], q[:, 2]
    record.array["point_source_id"] = source.source_id
    return record


def count_out(block: np.ndarray, ids: int) -> np.ndarray:
    """The points of `block` per point_source_id, 0 .. `ids` - 1."""
    return np.bincount(block["point_source_id"], minlength=ids)
