"""Fast-marching planning and exploration goals on hand-built grids."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from tidee.agent.mapping.geometry import GridSpec
from tidee.agent.navigation.explore import (
    FrontierExplorer,
    sample_reachable_goal,
    sample_unexplored_goal,
    unexplored_fraction,
)
from tidee.agent.navigation.fmm import FMMPlanner, NavStatus
from tidee.protocol.messages import ActionName as A

GRID = GridSpec.centred(256, 0.05)  # origin (-6.4, -6.4)


def cells_x(g: GridSpec, x0: float, x1: float) -> slice:
    return slice(g.to_cell((x0, 0.0))[0], g.to_cell((x1, 0.0))[0])


def cells_y(g: GridSpec, y0: float, y1: float) -> slice:
    return slice(g.to_cell((0.0, y0))[1], g.to_cell((0.0, y1))[1])


def wall_with_gap() -> np.ndarray:
    """A wall at x in [0, 0.2) across the whole grid except a gap at y in [1, 2)."""
    trav = np.ones(GRID.shape, dtype=bool)
    trav[cells_x(GRID, 0.0, 0.2), cells_y(GRID, -6.4, 1.0)] = False
    trav[cells_x(GRID, 0.0, 0.2), cells_y(GRID, 2.0, 6.4)] = False
    return trav


def step(pose: tuple[float, float, float], action: A, trav: np.ndarray) -> tuple[float, float, float]:
    """Simple kinematics: rotations always succeed, moves are blocked by non-traversible cells."""
    x, y, yaw = pose
    if action is A.RotateLeft:
        return (x, y, yaw + 90.0)
    if action is A.RotateRight:
        return (x, y, yaw - 90.0)
    assert action is A.MoveAhead, action
    nx, ny = x + 0.25 * math.cos(math.radians(yaw)), y + 0.25 * math.sin(math.radians(yaw))
    for t in np.linspace(0.0, 1.0, 11)[1:]:
        i, j = GRID.to_cell((x + t * (nx - x), y + t * (ny - y)))
        if not trav[i, j]:
            return pose
    return (nx, ny, yaw)


def drive(
    planner: FMMPlanner, trav: np.ndarray, pose: tuple[float, float, float], max_steps: int
) -> tuple[tuple[float, float, float], int, list[tuple[float, float]]]:
    visited = [pose[:2]]
    for n in range(max_steps):
        action = planner.next_action(*pose)
        if action is None:
            return pose, n, visited
        pose = step(pose, action, trav)
        visited.append(pose[:2])
    return pose, max_steps, visited


# ----------------------------------------------------------------------------- grid maths
def test_grid_cell_round_trip() -> None:
    assert GRID.to_cell((0.0, 0.0)) == (128, 128)
    assert GRID.to_cell((-6.4, -6.4)) == (0, 0)
    assert GRID.to_cell((-6.41, 0.0))[0] == -1
    assert GRID.to_world((128, 128)) == pytest.approx((0.025, 0.025))
    assert GRID.to_cell(GRID.to_world((17, 200))) == (17, 200)


# ----------------------------------------------------------------------------- fmm
def test_distance_goes_around_the_wall() -> None:
    trav = wall_with_gap()
    planner = FMMPlanner(trav, GRID)
    assert planner.set_goal((2.0, -2.0))
    d = planner.distance((-2.0, -2.0))
    straight = 4.0
    # Shortest detour through the gap corner (0, 1) and (0.2, 1): two legs + the wall width.
    detour = math.hypot(2.0, 3.0) + 0.2 + math.hypot(1.8, 3.0)
    assert d > straight + 3.0
    assert d == pytest.approx(detour, rel=0.05)
    # On the goal's side of the wall the field is euclidean.
    assert planner.distance((3.0, -2.0)) == pytest.approx(1.0, abs=0.08)
    assert planner.distance((2.0, -2.0)) == 0.0
    assert math.isinf(planner.distance((0.1, -2.0)))  # inside the wall


def test_path_avoids_the_wall_and_ends_at_goal() -> None:
    trav = wall_with_gap()
    planner = FMMPlanner(trav, GRID)
    planner.set_goal((2.0, -2.0))
    path = planner.path((-2.0, -2.0))
    assert path.dtype == np.float32 and path.ndim == 2 and path.shape[1] == 2
    assert np.allclose(path[0], (-1.975, -1.975))
    assert np.allclose(path[-1], (2.025, -1.975))
    cells = np.floor((path - np.array(GRID.origin)) / GRID.cell).astype(int)
    assert trav[cells[:, 0], cells[:, 1]].all()
    crossing = path[(path[:, 0] >= 0.0) & (path[:, 0] < 0.2)]  # points within the wall's x range
    assert len(crossing) > 0 and (crossing[:, 1] > 1.0).all() and (crossing[:, 1] < 2.0).all()
    short = planner.path((-2.0, -2.0), max_points=10)
    assert len(short) == 10 and np.allclose(short[[0, -1]], path[[0, -1]])


def test_next_action_reaches_goal_through_gap() -> None:
    trav = wall_with_gap()
    planner = FMMPlanner(trav, GRID)
    planner.set_goal((2.0, -2.0))
    pose, steps, visited = drive(planner, trav, (-2.0, -2.0, 0.0), max_steps=120)
    assert planner.status is NavStatus.arrived
    assert steps < 120
    assert planner.distance(pose[:2]) <= 0.25
    assert math.hypot(pose[0] - 2.0, pose[1] + 2.0) <= 0.3
    # It went through the gap.
    assert any(0.0 <= x <= 0.2 and 1.0 <= y <= 2.0 for x, y in visited)


def test_next_action_prefers_straight_and_turns_deterministically() -> None:
    trav = np.ones(GRID.shape, dtype=bool)
    planner = FMMPlanner(trav, GRID)
    planner.set_goal((2.0, 0.0))
    assert planner.next_action(0.0, 0.0, 0.0) is A.MoveAhead
    assert planner.next_action(0.0, 0.0, 90.0) is A.RotateRight
    assert planner.next_action(0.0, 0.0, -90.0) is A.RotateLeft
    assert planner.next_action(0.0, 0.0, 180.0) is A.RotateLeft  # tie: left wins
    assert planner.status is NavStatus.progress
    assert planner.next_action(1.9, 0.0, 0.0) is None and planner.status is NavStatus.arrived


def test_random_clutter_always_arrives() -> None:
    """Random furniture in a room, dilated by a 0.2 m radius: every goal is reached."""
    rng = np.random.default_rng(0)
    statuses: set[NavStatus] = set()
    for _ in range(20):
        occ = np.ones(GRID.shape, dtype=bool)
        occ[50:206, 50:206] = False
        for _ in range(12):
            i, j = rng.integers(50, 200, 2)
            w, h = rng.integers(5, 30, 2)
            occ[i : i + w, j : j + h] = True
        trav = ~ndimage.binary_dilation(occ, iterations=4)
        labels, _ = ndimage.label(trav)
        cells = np.argwhere(labels == np.argmax(np.bincount(labels.ravel())[1:]) + 1)
        start, goal = cells[rng.integers(len(cells), size=2)]
        planner = FMMPlanner(trav, GRID)
        planner.set_goal(GRID.to_world(goal))
        pose0 = (*GRID.to_world(start), float(rng.integers(4) * 90))
        pose = pose0
        for _ in range(400):
            action = planner.next_action(*pose)
            statuses.add(planner.status)
            if action is None:
                break
            pose = step(pose, action, trav)
        assert planner.status is NavStatus.arrived, (pose0, GRID.to_world(goal))
    assert NavStatus.detour in statuses  # the two-move fallback was exercised


def test_goal_inside_obstacle_snaps_next_to_it() -> None:
    trav = np.ones(GRID.shape, dtype=bool)
    trav[cells_x(GRID, 1.0, 2.0), cells_y(GRID, -0.5, 0.5)] = False  # a "table"
    planner = FMMPlanner(trav, GRID)
    assert planner.set_goal((1.5, 0.0), start_xy=(-1.0, 0.0))
    goal = planner.goal_mask
    assert goal.any() and not (goal & ~trav).any()
    # Goal cells hug the table: within the nearest distance from the goal cell's centre
    # (0.5 m, to the y = 0.5 side) + slack (0.25 m).
    gx, gy = GRID.to_world(GRID.to_cell((1.5, 0.0)))
    ii, jj = np.nonzero(goal)
    centres = np.array(GRID.origin) + (np.stack([ii, jj], 1) + 0.5) * GRID.cell
    dist = np.hypot(centres[:, 0] - gx, centres[:, 1] - gy)
    assert dist.min() == pytest.approx(0.5) and dist.max() <= 0.5 + 0.25 + 1e-9
    # Cells on all four sides of the table qualify.
    assert (centres[:, 0] < 1.0).any() and (centres[:, 0] > 2.0).any()
    assert (centres[:, 1] < -0.5).any() and (centres[:, 1] > 0.5).any()
    pose, steps, _ = drive(planner, trav, (-1.0, 0.0, 0.0), max_steps=60)
    assert planner.status is NavStatus.arrived
    assert math.hypot(pose[0] - 1.5, pose[1]) < 1.1


def test_unreachable_goal() -> None:
    trav = np.ones(GRID.shape, dtype=bool)
    # A closed box around the goal region.
    trav[cells_x(GRID, 1.0, 3.0), cells_y(GRID, -1.0, 1.0)] = False
    trav[cells_x(GRID, 1.2, 2.8), cells_y(GRID, -0.8, 0.8)] = True
    planner = FMMPlanner(trav, GRID)
    assert planner.set_goal((2.0, 0.0))
    assert math.isinf(planner.distance((0.0, 0.0)))
    assert planner.next_action(0.0, 0.0, 0.0) is None
    assert planner.status is NavStatus.unreachable and planner.stuck
    assert planner.path((0.0, 0.0)).shape == (0, 2)
    reach = planner.reachable_from((0.0, 0.0))
    assert reach[GRID.to_cell((-3.0, 0.0))] and not reach[GRID.to_cell((2.0, 0.0))]
    # With a start, snapping only considers cells reachable from it: the goal moves to the
    # outside of the box (1.0 m from the goal, within goal_snap_max_m = 1.5 m) ...
    assert planner.set_goal((2.0, 0.0), start_xy=(0.0, 0.0)) is True
    assert math.isfinite(planner.distance((0.0, 0.0)))
    assert not planner.goal_mask[GRID.to_cell((2.0, 0.0))]
    # ... unless that is farther than goal_snap_max_m: then there is no goal at all.
    strict = FMMPlanner(trav, GRID, goal_snap_max_m=0.5)
    assert strict.set_goal((2.0, 0.0), start_xy=(0.0, 0.0)) is False
    assert math.isinf(strict.distance((0.0, 0.0)))
    assert strict.next_action(0.0, 0.0, 0.0) is None and strict.status is NavStatus.unreachable


def test_goal_in_wall_snaps_only_to_reachable_side() -> None:
    trav = np.ones(GRID.shape, dtype=bool)
    trav[cells_x(GRID, 1.0, 1.3), :] = False  # an infinite wall
    planner = FMMPlanner(trav, GRID)
    assert planner.set_goal((1.15, 0.0), start_xy=(0.0, 0.0))
    ii, _ = np.nonzero(planner.goal_mask)
    assert (ii < GRID.to_cell((1.0, 0.0))[0]).all()
    assert math.isfinite(planner.distance((0.0, 0.0)))


def test_stuck_returns_a_rotation_and_flag() -> None:
    # The agent sits in a 0.2 m pocket, linked to the goal room only by a one-cell staircase
    # corridor heading towards +x, -y: every 0.25 m move is blocked, the distance is finite.
    trav = np.zeros(GRID.shape, dtype=bool)
    trav[126:130, 126:130] = True  # pocket around (0, 0) = cell (128, 128)
    for k in range(41):
        trav[129 + k, 126 - k] = True
        trav[130 + k, 126 - k] = True
    trav[165:185, 70:90] = True  # goal room
    planner = FMMPlanner(trav, GRID)
    planner.set_goal(GRID.to_world((175, 80)))
    assert math.isfinite(planner.distance((0.0, 0.0)))
    action = planner.next_action(0.0, 0.0, 0.0)
    assert planner.status is NavStatus.stuck and planner.stuck and planner.stuck_reason
    assert action is A.RotateRight  # downhill is at -45 degrees
    assert planner.next_action(0.0, 0.0, -90.0) is A.RotateLeft
    assert planner.next_action(0.0, 0.0, 100.0) is A.RotateRight  # the short way round
    assert planner.next_action(0.0, 0.0, 170.0) is A.RotateLeft


def test_crop_matches_full_field_near_known_region() -> None:
    trav = wall_with_gap()
    known = np.zeros(GRID.shape, dtype=bool)
    known[cells_x(GRID, -3.0, 3.0), cells_y(GRID, -3.0, 3.0)] = True
    full = FMMPlanner(trav, GRID)
    cropped = FMMPlanner(trav, GRID, known=known, crop_margin_m=1.0)
    full.set_goal((2.0, -2.0))
    cropped.set_goal((2.0, -2.0), start_xy=(-2.0, -2.0))
    assert cropped.crop is not None and cropped.crop != (0, 256, 0, 256)
    i0, i1, j0, j1 = cropped.crop
    assert (i1 - i0) * (j1 - j0) < 0.5 * 256 * 256
    for xy in [(-2.0, -2.0), (-1.0, 2.5), (2.5, 2.5), (1.0, -2.9)]:
        assert cropped.distance(xy) == pytest.approx(full.distance(xy), abs=1e-9)
    assert math.isinf(cropped.distance((-6.0, -6.0)))


def test_crop_to_goal_component_is_exact() -> None:
    # An enclosed room: fast marching only needs the room's bounding box.
    trav = np.zeros(GRID.shape, dtype=bool)
    trav[cells_x(GRID, -1.0, 3.0), cells_y(GRID, -2.0, 2.0)] = True
    planner = FMMPlanner(trav, GRID)
    planner.set_goal((2.0, 1.0))
    i0, i1, j0, j1 = planner.crop
    assert (i1 - i0, j1 - j0) == (80, 80)
    assert planner.distance((-0.5, 1.0)) == pytest.approx(2.5, abs=0.05)


def test_input_validation() -> None:
    with pytest.raises(ValueError, match="shape"):
        FMMPlanner(np.ones((10, 10), bool), GRID)
    with pytest.raises(TypeError, match="bool"):
        FMMPlanner(np.ones(GRID.shape, np.uint8), GRID)
    planner = FMMPlanner(np.ones(GRID.shape, bool), GRID)
    with pytest.raises(RuntimeError, match="set_goal"):
        planner.next_action(0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="outside the grid"):
        planner.set_goal((10.0, 0.0))


def test_goal_radius() -> None:
    planner = FMMPlanner(np.ones(GRID.shape, bool), GRID)
    planner.set_goal((1.0, 0.0), radius_m=0.5)
    assert planner.distance((0.6, 0.0)) == 0.0
    assert planner.distance((0.0, 0.0)) == pytest.approx(0.5, abs=0.06)


# ----------------------------------------------------------------------------- explore
def test_unexplored_fraction() -> None:
    reachable = np.zeros((10, 10), bool)
    reachable[:, :5] = True  # 50 cells
    explored = np.zeros((10, 10), bool)
    explored[:, :2] = True  # 20 of them explored
    explored[:, 8:] = True  # explored but unreachable: ignored
    assert unexplored_fraction(explored, reachable) == pytest.approx(30 / 50)
    assert unexplored_fraction(reachable, reachable) == 0.0
    assert unexplored_fraction(explored, np.zeros((10, 10), bool)) == 0.0
    with pytest.raises(ValueError, match="shape"):
        unexplored_fraction(explored, reachable[:5])


def test_sample_unexplored_goal_is_reachable_unexplored_and_seeded() -> None:
    g = GridSpec(origin=(0.0, 0.0), cell=0.1, shape=(40, 40))
    reachable = np.zeros(g.shape, bool)
    reachable[5:35, 5:35] = True
    explored = np.zeros(g.shape, bool)
    explored[5:20, 5:35] = True
    agent = (1.0, 1.0)
    goals = []
    for seed in range(20):
        xy = sample_unexplored_goal(explored, reachable, g, np.random.default_rng(seed), agent)
        assert xy is not None
        ij = g.to_cell(xy)
        assert reachable[ij] and not explored[ij]
        assert ij[0] == 20  # prefers the border with explored space
        assert math.dist(xy, agent) >= 0.5
        goals.append(xy)
    assert len(set(goals)) > 5
    again = sample_unexplored_goal(explored, reachable, g, np.random.default_rng(3), agent)
    assert again == goals[3]
    # Nothing unexplored reachable: None.
    assert sample_unexplored_goal(reachable, reachable, g, np.random.default_rng(0), agent) is None
    # min_dist excludes everything near the agent.
    far = sample_unexplored_goal(
        explored, reachable, g, np.random.default_rng(0), (2.05, 2.05), min_dist_m=10.0
    )
    assert far is None


def test_sample_unexplored_goal_falls_back_without_border() -> None:
    g = GridSpec(origin=(0.0, 0.0), cell=0.1, shape=(20, 20))
    reachable = np.zeros(g.shape, bool)
    reachable[10:15, 10:15] = True
    explored = np.zeros(g.shape, bool)  # nothing explored yet: no border cells
    xy = sample_unexplored_goal(explored, reachable, g, np.random.default_rng(1), (0.0, 0.0))
    assert xy is not None and reachable[g.to_cell(xy)]


def test_sample_reachable_goal() -> None:
    g = GridSpec(origin=(0.0, 0.0), cell=0.1, shape=(30, 30))
    reachable = np.zeros(g.shape, bool)
    reachable[0:30, 0:3] = True
    agent = (0.15, 0.15)
    for seed in range(10):
        xy = sample_reachable_goal(reachable, g, np.random.default_rng(seed), agent)
        assert xy is not None and reachable[g.to_cell(xy)] and math.dist(xy, agent) >= 1.0
    assert sample_reachable_goal(reachable, g, np.random.default_rng(5), agent) == sample_reachable_goal(
        reachable, g, np.random.default_rng(5), agent
    )
    assert sample_reachable_goal(reachable, g, np.random.default_rng(0), agent, min_dist_m=5.0) is None


def frontier_map() -> tuple[GridSpec, np.ndarray, np.ndarray, np.ndarray]:
    """Known free room x in [0, 3), y in [0, 3) with walls, two doorways to unknown space.

    West doorway (near the agent, long path) vs east doorway (farther in a straight line but
    a shorter geodesic is arranged by an inner wall), plus a 2-cell speck that is dropped.
    """
    g = GridSpec(origin=(0.0, 0.0), cell=0.1, shape=(50, 50))
    known = np.zeros(g.shape, bool)
    known[0:31, 0:31] = True
    obstacle = np.zeros(g.shape, bool)
    obstacle[30, 0:31] = True  # wall x = 3.0 (east)
    obstacle[0:31, 30] = True  # wall y = 3.0 (north)
    obstacle[30, 10:15] = False  # east doorway: 5 cells, y in [1.0, 1.5)
    obstacle[0:31, 30] = True
    obstacle[10:20, 30] = False  # north doorway: 10 cells, x in [1.0, 2.0)
    free = known & ~obstacle
    known[30, 10:15] = True
    known[10:20, 30] = True
    return g, free, known, obstacle


def test_frontier_clusters() -> None:
    g, free, known, obstacle = frontier_map()
    # A single unknown cell inside the room has a 4-cell frontier ring: below 5, dropped.
    known[5, 5] = False
    free[5, 5] = False
    explorer = FrontierExplorer(g, min_cluster_cells=5)
    clusters = explorer.frontiers(free, known, obstacle)
    assert [c.size for c in clusters] == [10, 5]
    north, east = clusters
    assert set(map(tuple, north.cells)) == {(i, 30) for i in range(10, 20)}
    assert set(map(tuple, east.cells)) == {(30, j) for j in range(10, 15)}
    assert east.centroid_xy == pytest.approx((3.05, 1.25))
    assert east.goal_xy == pytest.approx((3.05, 1.25))
    assert north.centroid_xy == pytest.approx((1.5, 3.05))
    assert north.goal_xy == pytest.approx((1.45, 3.05))  # first of the two nearest cells
    # The map edge is not a frontier.
    full = np.ones(g.shape, bool)
    assert explorer.frontiers(full, full, np.zeros(g.shape, bool)) == []


def test_frontier_next_goal_uses_geodesic_distance() -> None:
    g, free, known, obstacle = frontier_map()
    explorer = FrontierExplorer(g, min_cluster_cells=5)
    trav = ~obstacle
    agent = (2.55, 1.25)  # right next to the east doorway
    planner = FMMPlanner(trav, g)
    planner.set_goal(agent)
    assert explorer.next_goal(free, known, obstacle, planner, agent) == pytest.approx((3.05, 1.25))
    # Block the way east with an inner wall: the north doorway becomes geodesically nearer
    # even though the east doorway is nearer in a straight line.
    trav2 = trav.copy()
    trav2[27, 0:30] = False
    trav2[27, 0:2] = True  # a gap far south
    obstacle2 = ~trav2
    free2 = free & trav2
    agent2 = (2.55, 1.25)
    planner2 = FMMPlanner(trav2, g)
    planner2.set_goal(agent2)
    east_geo = float(planner2.distance_field[30, 10:15].min())
    north_geo = float(planner2.distance_field[10:20, 30].min())
    assert north_geo < east_geo
    goal = explorer.next_goal(free2, known, obstacle2, planner2.distance_field, agent2)
    assert goal is not None and goal[1] == pytest.approx(3.05)
    # No frontier left: None.
    full = np.ones(g.shape, bool)
    assert explorer.next_goal(full, full, np.zeros(g.shape, bool), planner, agent) is None


def test_a_way_too_narrow_for_the_moves_is_left_for_a_lattice_path() -> None:
    """The geodesic way to the goal leaves the agent's room by a one-cell staircase (the field
    is continuous; the agent moves 0.25 m along x or y). Greedy moves lead to its mouth and
    stop there; the search over the move lattice then finds the long corridor round, and the
    agent arrives. Before, it turned on the spot as "stuck" until its budget ran out."""
    trav = np.zeros(GRID.shape, dtype=bool)
    trav[120:137, 120:137] = True  # the agent's room around (0, 0) = cell (128, 128)
    for k in range(41):  # the staircase towards +x, -y
        trav[136 + k, 120 - k] = True
        trav[137 + k, 120 - k] = True
    trav[165:186, 70:91] = True  # the goal room
    trav[124:133, 136:201] = True  # the way round: +y, then +x, then -y
    trav[124:190, 192:201] = True
    trav[177:186, 70:201] = True
    planner = FMMPlanner(trav, GRID)
    planner.set_goal(GRID.to_world((175, 80)))
    straight = planner.distance((0.0, 0.0))
    assert math.isfinite(straight) and straight < 5.0  # the staircase is the geodesic way
    pose, steps, visited = drive(planner, trav, (0.0, 0.0, 0.0), max_steps=200)
    assert planner.status is NavStatus.arrived, (pose, steps)
    assert max(v[1] for v in visited) > 3.0  # it went round by the corridor
