"""Cloud-to-cloud distances of the report: a known offset between two scans of one surface is read
back, and measuring a seeded sample of the source keeps the figures of all its points."""

from __future__ import annotations

import numpy as np
from builders import plane_basis

from plotmosaic.config.report import DistanceConfig
from plotmosaic.report.distance import edge_distances, local_normals, target_index


def _surface(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on a gently rolling 20 m x 20 m ground: curved, so each local plane is its own."""
    xy = rng.uniform(0, 20, (n, 2))
    z = 0.5 * np.sin(xy[:, 0] / 3) + 0.3 * np.cos(xy[:, 1] / 4)
    return np.column_stack([xy, z])


def test_local_normals_are_the_planes_normals():
    rng = np.random.default_rng(0)
    normal, u, v = plane_basis([0.3, -0.2, 1.0])
    ab = rng.normal(size=(500, 6, 2))
    nb = ab[..., :1] * u + ab[..., 1:] * v + rng.normal(size=(500, 1, 3))
    centre, got = local_normals(nb)
    np.testing.assert_allclose(centre, nb.mean(axis=1), atol=1e-12)
    np.testing.assert_allclose(np.abs(got @ normal), 1.0, atol=1e-9)


def test_a_2_cm_lift_reads_2_cm_from_a_sample_as_from_all_points():
    rng = np.random.default_rng(1)
    clouds = {
        "target": _surface(rng, 200_000),
        "source": _surface(rng, 120_000) + [0, 0, 0.02],
    }
    whole = DistanceConfig(sample=len(clouds["source"]))
    cfg = DistanceConfig(sample=20_000)
    index = target_index(clouds["target"], cfg)
    src = clouds["source"]
    every = edge_distances("source", "target", src, index, whole, np.random.default_rng(0))
    part = edge_distances("source", "target", src, index, cfg, np.random.default_rng(0))
    assert len(every["distances"]) > 100_000
    assert 10_000 < len(part["distances"]) <= 20_000
    # the surface tilts by up to ~10 deg: the distance along its normal is 2 cm x cos(tilt)
    assert 0.0190 < every["median"] < 0.0201
    assert abs(part["median"] - every["median"]) < 0.0003
    assert abs(part["p90"] - every["p90"]) < 0.0005
    assert part["share"] > 0.95
    again = edge_distances("source", "target", src, index, cfg, np.random.default_rng(0))
    np.testing.assert_array_equal(again["distances"], part["distances"])  # seeded


def test_local_normals_of_lines_and_blobs_are_unit_eigenvectors():
    """Neighbours on a line (a double smallest eigenvalue), all in one point, or spread evenly:
    the normal is still a unit eigenvector of the smallest eigenvalue."""
    rng = np.random.default_rng(2)
    line = np.linspace(0, 1, 6)[:, None] * [1.0, 2.0, 0.5]
    cube = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [0.5, 0.5, 0.5]])
    nb = np.stack([line, np.zeros((6, 3)), cube, *rng.normal(size=(50, 6, 3))])
    _, normal = local_normals(nb)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-9)
    q = nb - nb.mean(axis=1, keepdims=True)
    scatter = np.einsum("nki,nkj->nij", q, q)
    smallest = np.linalg.eigvalsh(scatter)[:, 0]
    residual = np.einsum("nij,nj->ni", scatter, normal) - smallest[:, None] * normal
    np.testing.assert_allclose(residual, 0.0, atol=1e-9)
