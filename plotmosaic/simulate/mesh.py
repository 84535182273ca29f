"""Triangle soups with a semantic label (and an owner id) per triangle, and shape builders.

Labels: 0 ground, 1 stem/branch/log (woody), 2 foliage, 3 understory (grass, shrubs).
Everything is vectorised over many shapes at once, in the local frame near the origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GROUND, WOODY, FOLIAGE, UNDERSTORY = 0, 1, 2, 3
LABEL_NAMES = {GROUND: "ground", WOODY: "stem+branch", FOLIAGE: "foliage", UNDERSTORY: "understory"}


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # (V, 3) local frame (float32 once assembled: Embree's precision anyway)
    triangles: np.ndarray  # (T, 3) vertex indices (int32 once assembled)
    labels: np.ndarray  # (T,) uint8
    owners: np.ndarray  # (T,) int32: object id (tree, shrub, tuft, ...) or -1

    @classmethod
    def empty(cls) -> Mesh:
        return cls(
            np.zeros((0, 3)),
            np.zeros((0, 3), np.int64),
            np.zeros(0, np.uint8),
            np.zeros(0, np.int32),
        )

    @classmethod
    def soup(cls, corners: np.ndarray, label: int, owners: np.ndarray | int = -1) -> Mesh:
        """Independent triangles from (T, 3, 3) corner coordinates."""
        corners = np.asarray(corners, dtype=np.float64).reshape(-1, 3, 3)
        t = len(corners)
        owners = np.broadcast_to(np.asarray(owners, dtype=np.int32), (t,)).copy()
        return cls(
            corners.reshape(-1, 3),
            np.arange(3 * t, dtype=np.int64).reshape(t, 3),
            np.full(t, label, np.uint8),
            owners,
        )

    def __len__(self) -> int:
        return len(self.triangles)

    def select(self, keep: np.ndarray) -> Mesh:
        """Triangles where `keep` is true (vertices are kept as they are)."""
        return Mesh(self.vertices, self.triangles[keep], self.labels[keep], self.owners[keep])


def concat(meshes: list[Mesh]) -> Mesh:
    meshes = [m for m in meshes if len(m)]
    if not meshes:
        return Mesh.empty()
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(
        # local frame: float32 is exact enough
        np.concatenate([m.vertices for m in meshes], dtype=np.float32),
        np.concatenate([m.triangles + o for m, o in zip(meshes, offsets)], dtype=np.int32),
        np.concatenate([m.labels for m in meshes]),
        np.concatenate([m.owners for m in meshes]),
    )


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def orthonormal_frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to each (N, 3) axis and to each other."""
    axis = unit(np.atleast_2d(axis))
    helper = np.where(np.abs(axis[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = unit(np.cross(axis, helper))
    return u, np.cross(axis, u)


def tubes(
    paths: np.ndarray,
    radii: np.ndarray,
    sides: int,
    label: int,
    owners: np.ndarray,
    cap: bool = True,
) -> Mesh:
    """Tapered tubes along polylines: paths (N, R, 3) ring centres, radii (N, R); R >= 2 rings each.

    The ring frame is taken from each tube's overall axis so facets stay aligned and normals smooth.
    """
    paths = np.asarray(paths, dtype=np.float64)
    n, r, _ = paths.shape
    if n == 0:
        return Mesh.empty()
    u, v = orthonormal_frame(paths[:, -1] - paths[:, 0])
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    # (N, S, 3)
    ring = np.cos(ang)[None, :, None] * u[:, None, :] + np.sin(ang)[None, :, None] * v[:, None, :]
    verts = paths[:, :, None, :] + radii[:, :, None, None] * ring[:, None, :, :]  # (N, R, S, 3)
    i = np.arange(r - 1)[:, None]
    j = np.arange(sides)[None, :]
    a = i * sides + j
    b = i * sides + (j + 1) % sides
    c = a + sides
    d = b + sides
    quads = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )
    tris = [quads]
    extra = []
    if cap:  # close the top end with a fan to one extra vertex per tube
        top = r * sides
        tris.append(
            np.stack(
                [(r - 1) * sides + j[0], np.full(sides, top), (r - 1) * sides + (j[0] + 1) % sides],
                -1,
            )
        )
        extra = [paths[:, -1:, :]]
    per_tube = r * sides + (1 if cap else 0)
    base_verts = verts.reshape(n, r * sides, 3)
    all_verts = np.concatenate([base_verts] + extra, axis=1).reshape(-1, 3)
    local = np.concatenate(tris)
    triangles = (local[None, :, :] + (np.arange(n) * per_tube)[:, None, None]).reshape(-1, 3)
    t_each = len(local)
    return Mesh(
        all_verts,
        triangles,
        np.full(n * t_each, label, np.uint8),
        np.repeat(np.asarray(owners, np.int32), t_each),
    )


def random_elements(
    centres: np.ndarray,
    sizes: np.ndarray,
    rng: np.random.Generator,
    label: int,
    owners,
    quads: bool = False,
) -> Mesh:
    """Small triangles (needle clusters) or quads (leaves) at `centres`, randomly oriented."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    n = len(centres)
    if n == 0:
        return Mesh.empty()
    normal = unit(rng.normal(size=(n, 3)))
    u, v = orthonormal_frame(normal)
    s = np.asarray(sizes, dtype=np.float64)[:, None]
    owners = np.broadcast_to(np.asarray(owners, np.int32), (n,))
    if quads:
        p = [
            centres + s * (a * u + b * v) / 2
            for a, b in ((-1, -0.5), (1, -0.5), (1, 0.5), (-1, 0.5))
        ]
        corners = np.concatenate([np.stack([p[0], p[1], p[2]], 1), np.stack([p[0], p[2], p[3]], 1)])
        return Mesh.soup(corners, label, np.concatenate([owners, owners]))
    p = [centres + s * (np.cos(t) * u + np.sin(t) * v) / np.sqrt(3) for t in (0.0, 2.094, 4.189)]
    return Mesh.soup(np.stack(p, 1), label, owners)
