"""MovingNearest: an ICP run's correspondence search keeps still points' neighbours, exactly."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.align.icp import MovingNearest


def test_moving_points_get_the_neighbours_and_distances_of_a_full_query():
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(*[np.arange(0.0, 3.0, 0.05)] * 3), axis=-1).reshape(-1, 3)
    target = np.vstack([grid, rng.uniform(0, 3, (20_000, 3))])  # ties on the grid, none off it
    tree = cKDTree(target)
    points = rng.uniform(0, 3, (5_000, 3))
    search = MovingNearest(tree)
    # steps from decimetres down to micrometres, bounds narrowing and widening again
    for step, bound in [
        (0.1, 0.3),
        (0.02, 0.3),
        (0.002, 0.1),
        (1e-4, 0.05),
        (1e-6, 0.02),
        (1e-6, 0.3),
    ]:
        points = points + rng.normal(0, step, points.shape)
        got_d, got_j = search(points, bound)
        want_d, want_j = tree.query(points, distance_upper_bound=bound)
        assert np.array_equal(got_j, want_j)
        assert got_d.tobytes() == want_d.tobytes()


def test_points_on_the_grid_itself_are_queried_again_not_guessed():
    # every point sits on a tree point: distance 0, the second nearest 5 cm away; moving a point by
    # half the spacing makes two grid points equally near, which only a query may decide
    grid = np.stack(np.meshgrid(*[np.arange(0.0, 1.0, 0.05)] * 3), axis=-1).reshape(-1, 3)
    tree = cKDTree(grid)
    search = MovingNearest(tree)
    search(grid[:200], 0.2)
    moved = grid[:200] + [0.025, 0.0, 0.0]
    got_d, got_j = search(moved, 0.2)
    want_d, want_j = tree.query(moved, distance_upper_bound=0.2)
    assert np.array_equal(got_j, want_j) and np.array_equal(got_d, want_d)


def test_points_beyond_the_distance_drifting_into_it_and_on_it():
    # points start outside the search distance (their nearest known from the wider look) and walk
    # in across it; some sit exactly on it, where only the tree's own test may decide
    rng = np.random.default_rng(3)
    target = rng.uniform(-0.2, 0.2, (400, 3))
    target[0] = 5.0  # alone: the points placed around it have it as their nearest
    tree = cKDTree(target)
    direction = rng.normal(size=(3000, 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    start = direction * rng.uniform(0.45, 0.9, (3000, 1))
    search = MovingNearest(tree)
    for step in range(40):
        points = start * (1.0 - 0.02 * step)
        points[:3] = [[5.25, 5.0, 5.0], [5.0, 4.75, 5.0], [5.0, 5.0, 5.125]]  # on the distance
        bound = 0.25 if step % 10 else 0.125  # the bound narrowing and widening again
        got_d, got_j = search(points, bound)
        want_d, want_j = tree.query(points, distance_upper_bound=bound)
        assert np.array_equal(got_j, want_j)
        assert got_d.tobytes() == want_d.tobytes()
    assert np.isfinite(want_d).sum() > 100  # most of them walked into reach
