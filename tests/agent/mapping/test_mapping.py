"""Geometry and the semantic mapper, on synthetic renders of a box world with known geometry."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from tidee.agent.mapping import FREE, OBSTACLE, GridSpec, MapConfig, SemanticMapper, project, unproject
from tidee.agent.perception.base import Detection
from tidee.protocol.messages import Observation

CAM_H = 0.9


# ----------------------------------------------------------------------------- synthetic world
def intrinsics(res: int) -> np.ndarray:
    f = (res / 2) / math.tan(math.radians(45))
    return np.array([[f, 0, (res - 1) / 2], [0, f, (res - 1) / 2], [0, 0, 1.0]])


def camera_pose(x: float, y: float, yaw_deg: float, pitch_deg: float, h: float = CAM_H) -> np.ndarray:
    """Optical (x right, y down, z forward) -> start frame, built by hand from yaw and pitch."""
    yaw, th = math.radians(yaw_deg), math.radians(pitch_deg)
    fwd = np.array([math.cos(yaw) * math.cos(th), math.sin(yaw) * math.cos(th), -math.sin(th)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    t = np.eye(4)
    t[:3, 0], t[:3, 1], t[:3, 2], t[:3, 3] = right, down, fwd, [x, y, h]
    return t


@dataclass
class World:
    """A room [x0, x1] x [y0, y1] with a floor at z = 0, four walls, and axis-aligned boxes."""

    room: tuple[float, float, float, float] = (-3.0, 3.5, -2.5, 3.0)
    boxes: tuple[tuple[np.ndarray, np.ndarray], ...] = (
        (np.array([1.0, -0.4, 0.0]), np.array([1.6, 0.4, 0.7])),
    )

    def render(self, pose: np.ndarray, k: np.ndarray, res: int) -> tuple[np.ndarray, np.ndarray]:
        """(depth float32 res x res along the optical axis, int HxW: index of the box hit, -1 none)."""
        vv, uu = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
        rays = np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu, float)], -1)
        d = rays.reshape(-1, 3) @ pose[:3, :3].T  # world directions; t along them = optical depth
        o = pose[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            best = np.full(d.shape[0], np.inf)
            t_floor = np.where(d[:, 2] < 0, -o[2] / d[:, 2], np.inf)
            best = np.minimum(best, t_floor)
            x0, x1, y0, y1 = self.room
            for axis, lo, hi in ((0, x0, x1), (1, y0, y1)):
                t_lo = np.where(d[:, axis] < 0, (lo - o[axis]) / d[:, axis], np.inf)
                t_hi = np.where(d[:, axis] > 0, (hi - o[axis]) / d[:, axis], np.inf)
                best = np.minimum(best, np.minimum(t_lo, t_hi))
            hit = np.full(d.shape[0], -1)
            for b, (lo, hi) in enumerate(self.boxes):
                ta = (lo - o) / d
                tb = (hi - o) / d
                t_near = np.nanmax(np.minimum(ta, tb), axis=1)
                t_far = np.nanmin(np.maximum(ta, tb), axis=1)
                ok = (t_near <= t_far) & (t_near > 0) & (t_near < best)
                best = np.where(ok, t_near, best)
                hit[ok] = b
        return best.reshape(res, res).astype(np.float32), hit.reshape(res, res)


def observe(
    world: World, x: float, y: float, yaw: float, pitch: float = 30.0, res: int = 128, step: int = 0
) -> tuple[Observation, np.ndarray]:
    k = intrinsics(res)
    pose = camera_pose(x, y, yaw, pitch)
    depth, hit = world.render(pose, k, res)
    obs = Observation(
        session="t",
        step=step,
        rgb=np.zeros((res, res, 3), np.uint8),
        depth=depth,
        camera_pose=pose,
        agent_pose=(x, y, yaw, pitch),
        intrinsics=k,
    )
    return obs, hit


def cells_of(grid: GridSpec, x0: float, x1: float, y0: float, y1: float) -> tuple[slice, slice]:
    """Index slices of the cells whose centres lie in [x0, x1] x [y0, y1]."""
    i0, j0 = grid.world_to_cell(np.array([[x0, y0]]))[0] + 1
    i1, j1 = grid.world_to_cell(np.array([[x1, y1]]))[0]
    return slice(i0, i1), slice(j0, j1)


# ----------------------------------------------------------------------------- geometry
def test_unproject_floor_plane_and_round_trip() -> None:
    res = 64
    k = intrinsics(res)
    pose = camera_pose(0.3, -0.2, 40.0, 60.0)  # pitched 60 down, 90 FOV: every ray hits the floor
    depth, _ = World(room=(-50, 50, -50, 50), boxes=()).render(pose, k, res)
    pts, pix = unproject(depth, k, pose, max_depth=100.0)
    assert pts.dtype == np.float32 and pts.shape == (res * res, 3)
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-4)
    u, v, z = project(pts, k, pose)
    np.testing.assert_allclose(u, pix % res, atol=1e-3)
    np.testing.assert_allclose(v, pix // res, atol=1e-3)
    np.testing.assert_allclose(z, depth.ravel()[pix], rtol=1e-5)


def test_unproject_wall_at_known_distance() -> None:
    res = 32
    k = intrinsics(res)
    pose = camera_pose(0.0, 0.5, 90.0, 0.0)  # looking along +y (image right = +x) at y = 2.5
    depth = np.full((res, res), 2.0, np.float32)  # a wall 2 m ahead, facing the camera
    pts, pix = unproject(depth, k, pose, stride=2)
    assert pts.shape[0] == (res // 2) ** 2
    np.testing.assert_allclose(pts[:, 1], 2.5, atol=1e-4)
    assert np.all((pix % res) % 2 == 0) and np.all((pix // res) % 2 == 0)
    # pixel (16, 16), half a pixel right of and below the principal point, 2 m ahead
    centre = pts[(pix % res == 16) & (pix // res == 16)][0]
    expected = [2.0 * (16 - k[0, 2]) / k[0, 0], 2.5, CAM_H - 2.0 * (16 - k[1, 2]) / k[1, 1]]
    np.testing.assert_allclose(centre, expected, atol=1e-4)


def test_unproject_drops_invalid_depths_and_honours_mask() -> None:
    k = intrinsics(4)
    depth = np.array(
        [[0.0, np.nan, np.inf, 0.04], [1.0, 11.0, -1.0, 2.0], [1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]],
        np.float32,
    )
    _, pix = unproject(depth, k, np.eye(4), max_depth=10.0)
    assert sorted(pix[:2].tolist()) == [4, 7] and pix.size == 10
    mask = np.zeros((4, 4), bool)
    mask[1, 3] = mask[0, 0] = True
    _, pix = unproject(depth, k, np.eye(4), mask=mask)
    assert pix.tolist() == [7]
    with pytest.raises(ValueError, match="mask shape"):
        unproject(depth, k, np.eye(4), mask=np.ones((3, 3), bool))


def test_a_masked_unprojection_gives_the_points_of_the_full_one() -> None:
    # a mask takes the few pixels' rays alone: the same points, in the same order
    res = 48
    k = intrinsics(res)
    pose = camera_pose(0.3, -0.2, 40.0, 30.0)
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.2, 6.0, (res, res)).astype(np.float32)
    depth[rng.random((res, res)) < 0.1] = 0.0
    mask = rng.random((res, res)) < 0.2
    pts, pix = unproject(depth, k, pose, mask=mask)
    full, full_pix = unproject(depth, k, pose)
    keep = mask.ravel()[full_pix]
    np.testing.assert_array_equal(pix, full_pix[keep])
    np.testing.assert_array_equal(pts, full[keep])


def test_project_behind_camera_is_nan() -> None:
    u, v, z = project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0]]), intrinsics(8), np.eye(4))
    assert np.isnan(u[0]) and np.isnan(v[0]) and z[0] == -1.0
    assert u[1] == pytest.approx(3.5) and v[1] == pytest.approx(3.5)


def test_gridspec_follows_mapsnapshot_convention() -> None:
    g = GridSpec((-1.0, 2.0), 0.5, (4, 6))
    ij = g.world_to_cell(np.array([[-1.0, 2.0], [-0.99, 2.51], [0.999, 4.99], [1.0, 2.0], [-1.01, 2.0]]))
    assert ij.tolist() == [[0, 0], [0, 1], [3, 5], [4, 0], [-1, 0]]
    assert g.in_bounds(ij).tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(g.cell_to_world(np.array([[0, 0], [3, 5]])), [[-0.75, 2.25], [0.75, 4.75]])
    assert g.world_to_cell(g.cell_to_world(np.array([[2, 3]]))).tolist() == [[2, 3]]
    d = g.disc((0.0, 3.0), 0.5)  # centre on a corner shared by 4 cells
    assert sorted(map(tuple, d.tolist())) == [(1, 1), (1, 2), (2, 1), (2, 2)]
    with pytest.raises(ValueError, match="cell must be > 0"):
        GridSpec((0, 0), 0.0, (2, 2))


def test_map_config_defaults_and_validation() -> None:
    cfg = MapConfig()
    assert cfg.nav_shape == (256, 256) and cfg.voxel_shape == (128, 128, 64)
    with pytest.raises(ValueError, match="whole number"):
        MapConfig(nav_cell=0.07)
    with pytest.raises(ValueError, match="obstacle_z"):
        MapConfig(obstacle_z=(1.0, 0.5))
    with pytest.raises(ValueError, match="explored_threshold"):
        MapConfig(explored_threshold=0)
    with pytest.raises(ValueError, match="classes must be unique"):
        SemanticMapper(MapConfig(), ["Mug", "Mug"])


# ----------------------------------------------------------------------------- maps
@pytest.fixture(scope="module")
def rotated_in_place() -> SemanticMapper:
    """The agent at the start pose turns 4 x 90 degrees, pitched 30 degrees down."""
    world = World()
    m = SemanticMapper(MapConfig(), ["Box"])
    for s, yaw in enumerate((0.0, 90.0, 180.0, 270.0)):
        obs, _ = observe(world, 0.0, 0.0, yaw, res=256, step=s)
        m.update(obs, [])
    return m


def test_box_and_walls_become_obstacles(rotated_in_place: SemanticMapper) -> None:
    m, g = rotated_in_place, rotated_in_place.grid
    occ = m.occupancy_grid()
    # the box's front face (x = 1.0) is seen head-on: every cell along it is an obstacle
    si, sj = cells_of(g, 0.99, 1.06, -0.35, 0.35)
    assert occ[si, sj].size > 0 and np.all(occ[si, sj] == OBSTACLE)
    # each wall: all cells along it (away from corners) are obstacles, within one cell of the plane
    x0, x1, y0, y1 = World().room
    e = 0.08  # about one cell either side of the wall plane
    walls = (
        (x1 - e, x1 + e, y0 + 1, y1 - 1, 1),
        (x0 - e, x0 + e, y0 + 1, y1 - 1, 1),
        (x0 + 1, x1 - 1, y1 - e, y1 + e, 0),
        (x0 + 1, x1 - 1, y0 - e, y0 + e, 0),
    )
    for lo_x, hi_x, lo_y, hi_y, along in walls:
        band = m.obstacle[cells_of(g, lo_x, hi_x, lo_y, hi_y)]  # axis `along` runs along the wall
        assert band.shape[along] > 40 and np.all(band.any(axis=1 - along))
    # nothing beyond the walls, nothing in the open floor between agent and walls
    assert not m.obstacle[cells_of(g, x1 + 0.1, 6.0, -6.0, 6.0)].any()
    assert not m.obstacle[cells_of(g, -2.5, 0.8, -2.0, 2.5)].any()


def test_floor_is_free_and_explored(rotated_in_place: SemanticMapper) -> None:
    m, g = rotated_in_place, rotated_in_place.grid
    centres = g.cell_to_world(np.argwhere(np.ones(g.shape, bool))).reshape(g.shape + (2,))
    r = np.linalg.norm(centres, axis=-1)
    ring = (r > 0.4) & (r < 1.0)
    assert m.explored[ring].mean() > 0.95 and m.floor_seen[ring].mean() > 0.95
    assert (m.occupancy_grid()[ring] == FREE).mean() > 0.95
    assert not m.explored[cells_of(g, 3.6, 6.0, -6.0, 6.0)].any()  # beyond the +x wall
    assert m.seen_count.max() >= 2  # overlapping views counted


def test_traversible_blocks_box_keeps_agent_area(rotated_in_place: SemanticMapper) -> None:
    m, g = rotated_in_place, rotated_in_place.grid
    trav = m.traversible(agent_radius=0.2)
    assert not trav[cells_of(g, 0.85, 1.6, -0.55, 0.55)].any()  # the box grown by the radius
    centres = g.cell_to_world(np.argwhere(np.ones(g.shape, bool))).reshape(g.shape + (2,))
    assert trav[np.linalg.norm(centres, axis=-1) < 0.5].all()
    assert trav[cells_of(g, 4.0, 6.0, 4.0, 6.0)].all()  # unknown: optimistic
    assert m.traversible_at(np.array([[0.0, 0.0], [1.3, 0.0], [9.0, 0.0]])).tolist() == [True, False, False]


def test_views_from_different_poses_land_on_the_same_wall_cells() -> None:
    world = World(boxes=())
    hits = []
    for x, y, yaw in ((0.0, 0.0, 0.0), (-1.0, 0.8, 25.0), (1.5, -0.5, -10.0)):
        m = SemanticMapper(MapConfig(), [])
        m.update(observe(world, x, y, yaw, pitch=0.0)[0], [])
        ij = np.argwhere(m.obstacle)
        assert ij.size
        xy = m.grid.cell_to_world(ij)
        near = (np.abs(xy[:, 0] - 3.5) < 0.3) & (np.abs(xy[:, 1]) < 2.0)  # away from the corners
        assert near.sum() > 20
        wall_i = set(m.grid.world_to_cell(np.array([[3.499, 0], [3.5, 0]]))[:, 0].tolist())
        assert set(np.unique(ij[near, 0]).tolist()) <= wall_i
        hits.append((ij[near, 1].min(), ij[near, 1].max()))
    # the three views overlap along the wall (over 1 m) and there all put it in the same column
    assert min(h[1] for h in hits) - max(h[0] for h in hits) > 20


def test_obstacles_persist_until_cleared_and_stamps() -> None:
    m = SemanticMapper(MapConfig(), [])
    m.update(observe(World(), 0.0, 0.0, 0.0)[0], [])
    si, sj = cells_of(m.grid, 0.99, 1.06, -0.3, 0.3)
    assert m.obstacle[si, sj].all()
    m.update(observe(World(boxes=()), 0.0, 0.0, 0.0)[0], [])  # the box is gone: floor there
    assert m.obstacle[si, sj].all()
    m.clear_obstacle((1.02, 0.0), 0.5)
    assert not m.obstacle[si, sj].any()
    m.stamp_obstacle((-1.0, -1.0), 0.1)
    ij = m.grid.world_to_cell(np.array([[-1.0, -1.0]]))[0]
    assert m.occupancy_grid()[ij[0], ij[1]] == OBSTACLE
    assert not m.traversible_at(np.array([[-1.0, -1.0], [-1.25, -1.0]])).any()
    # the agent's own disc is free even where an obstacle point falls in it (looking steeply down)
    ij = m.grid.world_to_cell(np.array([[0.11, 0.0]]))[0]
    assert np.hypot(*(m.grid.cell_to_world(ij[None])[0])) < 0.15
    m.update(
        observe(
            World(boxes=((np.array([0.1, -0.05, 0.0]), np.array([0.14, 0.05, 0.4])),)),
            0.0,
            0.0,
            0.0,
            pitch=60.0,
        )[0],
        [],
    )
    assert m.obstacle[ij[0], ij[1]]  # the point was there ...
    assert m.occupancy_grid()[ij[0], ij[1]] == FREE  # ... but the agent stands there
    assert m.traversible(0.2)[tuple(m.grid.world_to_cell(np.zeros((1, 2)))[0])]
    m.reset()
    assert not m.obstacle.any() and not m.occupancy.any() and len(m.memory) == 0


def _noisy(obs: Observation, rng: np.random.Generator, sigma: float) -> Observation:
    """``obs`` with each depth scaled by 1 + N(0, sigma): a depth network's kind of error."""
    depth = obs.depth * (1.0 + rng.normal(0.0, sigma, obs.depth.shape)).astype(np.float32)
    return Observation(
        session=obs.session,
        step=obs.step,
        rgb=obs.rgb,
        depth=depth,
        camera_pose=obs.camera_pose,
        agent_pose=obs.agent_pose,
        intrinsics=obs.intrinsics,
    )


def test_carving_takes_away_an_obstacle_that_later_views_see_through() -> None:
    kept, carved = SemanticMapper(MapConfig(), []), SemanticMapper(MapConfig(carve=True), [])
    box, gone = World(), World(boxes=())
    assert MapConfig().carve_min_hits == 3
    seq = [(box, False), (box, False), (box, True), (gone, True), (gone, True), (gone, False)]
    for step, (world, held) in enumerate(seq):
        for m in (kept, carved):
            m.update(observe(world, 0.0, 0.0, 0.0, res=256, step=step)[0], [])
        si, sj = cells_of(kept.grid, 0.99, 1.06, -0.3, 0.3)  # the box's face
        assert kept.obstacle[si, sj].all()
        # an obstacle once three frames saw the box, until as many saw through where it stood
        assert carved.obstacle[si, sj].all() if held else not carved.obstacle[si, sj].any()
    # a blocked move's stamp is not carved; clearing forgets the points too
    carved.stamp_obstacle((-1.0, -1.0), 0.1)
    carved.update(observe(gone, 0.0, 0.0, 225.0, res=256, step=4)[0], [])
    ij = carved.grid.world_to_cell(np.array([[-1.0, -1.0]]))[0]
    assert carved.occupancy_grid()[ij[0], ij[1]] == OBSTACLE
    carved.clear_obstacle((-1.0, -1.0), 0.2)
    carved.update(observe(gone, 0.0, 0.0, 225.0, res=256, step=5)[0], [])
    assert not carved.obstacle[ij[0], ij[1]]


def test_carving_keeps_walls_and_box_and_clears_noise_on_the_floor() -> None:
    """Noisy depth (10 % per pixel, about a depth network's error) seen from three standpoints:
    without carving the open floor fills with raised floor points for good; with it they go,
    and the box and walls stay."""
    rng = np.random.default_rng(3)
    world = World()
    kept, carved = SemanticMapper(MapConfig(), ["Box"]), SemanticMapper(MapConfig(carve=True), ["Box"])
    step = 0
    for x, y in ((0.0, 0.0), (-1.0, 1.0), (-1.5, -1.2)):
        for yaw in range(0, 360, 45):
            for pitch in (30.0, 60.0):
                obs = _noisy(observe(world, x, y, yaw, pitch=pitch, res=256, step=step)[0], rng, 0.10)
                kept.update(obs, [])
                carved.update(obs, [])
                step += 1
    g = kept.grid
    open_floor = cells_of(g, -2.5, 0.7, -2.0, 2.5)
    assert kept.obstacle[open_floor].sum() > 1000
    assert carved.obstacle[open_floor].sum() * 100 < kept.obstacle[open_floor].sum()
    front = cells_of(g, 0.9, 1.1, -0.35, 0.35)  # the box's face, give or take the noise
    assert carved.obstacle[front].any(axis=0).all()
    x0, x1, y0, y1 = world.room
    e = 0.15
    for lo_x, hi_x, lo_y, hi_y, along in (
        (x0 - e, x0 + e, y0 + 1, y1 - 1, 1),  # the -x wall
        (x0 + 1, x1 - 1.5, y1 - e, y1 + e, 0),  # the +y wall
        (x0 + 1, x1 - 1.5, y0 - e, y0 + e, 0),  # the -y wall
    ):
        band = carved.obstacle[cells_of(g, lo_x, hi_x, lo_y, hi_y)]
        assert band.any(axis=1 - along).mean() > 0.95


def test_when_the_map_carves() -> None:
    from tidee.agent.config import AgentConfig
    from tidee.agent.mapping.config import wants_carving

    assert wants_carving("auto", "estimated") and not wants_carving("auto", "sensor")
    assert wants_carving("on", "sensor") and not wants_carving("off", "estimated")
    with pytest.raises(ValueError, match="carve must be one of"):
        AgentConfig(carve="always")  # type: ignore[arg-type]
    for bad in (dict(carve_min_hits=0), dict(carve_stride=0), dict(carve_z=0.0)):
        with pytest.raises(ValueError, match="MapConfig.carve"):
            MapConfig(**bad)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- detections
def test_detection_centroid_is_the_median_depth_surface_point() -> None:
    world = World()
    lo, hi = world.boxes[0]
    obs, hit = observe(world, 0.0, 0.3, -10.0, res=128, step=5)
    mask = hit == 0
    ys, xs = np.nonzero(mask)
    box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
    det = Detection("Box", 0.8, box, mask=mask, oop_prob=0.3)
    m = SemanticMapper(MapConfig(), ["Mug", "Box"])
    touched = m.update(obs, [det])
    assert len(touched) == 1 and len(m.memory) == 1 and m.last_track_ids == [touched[0].id]
    o = touched[0]
    assert o.label == "Box" and o.first_seen == 5 and o.oop_prob == pytest.approx(0.3)
    # on the box's visible surface, at the region's median depth
    assert np.all(o.centroid >= lo - 1e-3) and np.all(o.centroid <= hi + 1e-3)
    gap = np.minimum(np.abs(o.centroid - lo), np.abs(o.centroid - hi)).min()
    assert gap < 1e-3
    z = project(o.centroid[None], obs.intrinsics, obs.camera_pose)[2][0]
    assert abs(z - np.median(obs.depth[mask])) < 0.1 / 2
    # the 5-95 % box lies within the true box (one voxel of slack)
    assert np.all(o.box_min >= lo - 0.1) and np.all(o.box_max <= hi + 0.1)
    # voxels labelled "Box" are on the box
    pts, labels = m.voxel_points()
    on_box = pts[labels == 1]
    assert on_box.shape[0] > 10 and not (labels == 0).any()
    assert np.all(on_box >= lo - 0.1) and np.all(on_box <= hi + 0.1)
    # seen again from nearby: merges into the same entry
    obs2, hit2 = observe(world, 0.0, 0.0, 0.0, res=128, step=6)
    m.update(obs2, [Detection("Box", 0.9, (0, 0, 128, 128), mask=hit2 == 0)])
    assert len(m.memory) == 1 and o.n_obs == 2 and o.last_seen == 6


def test_passable_detections_are_mapped_but_never_obstacles() -> None:
    """A pickupable thing on the floor (here the box, detected as a "Dumbbell") is passed by
    the body: its points fill voxels and the memory, not the obstacle map."""
    world = World()
    obs, hit = observe(world, 0.0, 0.0, 0.0, res=128)
    mask = hit == 0
    ys, xs = np.nonzero(mask)
    det = Detection(
        "Dumbbell", 0.9, (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1), mask=mask
    )
    front = cells_of(SemanticMapper().grid, 0.99, 1.06, -0.35, 0.35)
    blocked = SemanticMapper(MapConfig(), ["Dumbbell"])
    blocked.update(obs, [det])
    passed = SemanticMapper(MapConfig(), ["Dumbbell"], passable={"Dumbbell"})
    passed.update(obs, [det])
    assert blocked.obstacle[front].any() and not passed.obstacle[front].any()
    assert passed.obstacle.sum() > 0  # the walls still are obstacles
    assert passed.occupancy.sum() == blocked.occupancy.sum() and len(passed.memory) == 1


def test_detection_without_enough_depth_is_skipped() -> None:
    obs, _ = observe(World(), 0.0, 0.0, 0.0, res=64)
    obs.depth[:10, :10] = 0.0
    m = SemanticMapper(MapConfig(), ["Box"])
    assert m.update(obs, [Detection("Box", 0.9, (0, 0, 10, 10))]) == []
    assert m.last_track_ids == [None] and len(m.memory) == 0
    with pytest.raises(ValueError, match="region shape"):
        m.update(obs, [Detection("Box", 0.9, (0, 0, 1, 1), mask=np.ones((3, 3), bool))])


# ----------------------------------------------------------------------------- semantics
def test_semantic_volume_puts_mass_at_the_centroid() -> None:
    m = SemanticMapper(MapConfig(), ["Mug", "Bowl"])
    c = np.array([1.23, -0.47, 0.8])
    m.memory.add_or_merge("Mug", 0.9, c, c - 0.05, c + 0.05, 0)
    vol = m.semantic_volume(z_bins=8)
    assert vol.shape == (2, 8, 128, 128) and vol.dtype == np.float32
    expected = (int((0.8 + 0.1) // 0.4), int((1.23 + 6.4) // 0.1), int((-0.47 + 6.4) // 0.1))
    assert np.unravel_index(np.argmax(vol[0]), vol[0].shape) == expected
    assert vol[0][expected] == pytest.approx(1.0, rel=1e-5)
    assert vol[0].sum() > 1.5  # dilated, not a single voxel
    assert not vol[1].any()  # no bowls, nothing occupied
    top = m.semantic_topdown("Mug")
    assert top.shape == (128, 128) and np.unravel_index(np.argmax(top), top.shape) == expected[1:]
    # with occupancy: every channel carries it, the mug channel adds its bump
    m.update(observe(World(), 0.0, 0.0, 0.0)[0], [])
    vol2 = m.semantic_volume(z_bins=8)
    np.testing.assert_allclose(vol2[0] - vol2[1], vol[0], atol=1e-6)
    assert vol2[1].max() == 1.0 and vol2[1].sum() > 0
    with pytest.raises(ValueError, match="z_bins must divide"):
        m.semantic_volume(z_bins=7)


def test_snapshot_matches_maps() -> None:
    m = SemanticMapper(MapConfig(), ["Box"])
    m.update(observe(World(), 0.0, 0.0, 0.0)[0], [])
    snap = m.snapshot("s", 3)
    assert snap.origin == (-6.4, -6.4) and snap.cell == 0.05 and snap.voxel_size == 0.1
    assert snap.occupancy.shape == (256, 256) and snap.points.shape[0] == snap.point_labels.shape[0] > 0
    np.testing.assert_array_equal(snap.occupancy, m.occupancy_grid())


def test_labels_outside_classes_are_tracked_but_label_no_voxels() -> None:
    obs, hit = observe(World(), 0.0, 0.0, 0.0, res=64)
    m = SemanticMapper(MapConfig(), ["Mug"])
    touched = m.update(obs, [Detection("Lamp", 0.7, (0, 0, 64, 64), mask=hit == 0)])
    assert [o.label for o in touched] == ["Lamp"]
    assert not (m.voxel_labels >= 0).any() and m.occupancy.any()


# ----------------------------------------------------------------------------- percentiles
@pytest.mark.parametrize("n", [1, 2, 3, 5, 19, 20, 21, 100, 101, 4097])
def test_column_percentiles_equal_numpy_bit_for_bit(n: int) -> None:
    """The mapper's object boxes come from ``column_percentiles``: it must give exactly what
    ``np.percentile(..., axis=0)`` gives, on spread values, ties and tiny samples alike."""
    from tidee.agent.mapping.geometry import column_percentiles

    rng = np.random.default_rng(n)
    samples = [
        rng.normal(size=(n, 3)) * rng.uniform(0.01, 10.0, size=3) + rng.uniform(-5, 5, size=3),
        np.round(rng.uniform(0, 2, size=(n, 3)), 1),  # many ties
        np.full((n, 3), 0.3),
    ]
    for pts in samples:
        original = pts.copy()
        for lo_q, hi_q in ((5.0, 95.0), (2.0, 98.0), (0.0, 100.0), (50.0, 50.0)):
            lo, hi = column_percentiles(pts, lo_q, hi_q)
            want_lo, want_hi = np.percentile(pts, [lo_q, hi_q], axis=0)
            assert lo.tobytes() == want_lo.tobytes() and hi.tobytes() == want_hi.tobytes(), (n, lo_q, hi_q)
        np.testing.assert_array_equal(pts, original)  # the input is left as it was


def test_column_percentiles_refuse_no_points() -> None:
    from tidee.agent.mapping.geometry import column_percentiles

    with pytest.raises(ValueError, match="at least one point"):
        column_percentiles(np.zeros((0, 3)), 5.0, 95.0)
