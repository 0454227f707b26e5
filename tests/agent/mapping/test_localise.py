"""Scan matching against the map: a drifted pose is pulled back onto the mapped room."""

import math

import numpy as np
import pytest

from tidee.agent.config import AgentConfig
from tidee.agent.mapping.config import MapConfig
from tidee.agent.mapping.geometry import GridSpec
from tidee.agent.mapping.localise import Correction, ScanLocaliser, wants_localiser
from tidee.protocol.messages import Observation

EYE = 0.9
SIZE = 256  # pixels a side, as the agent sees
HALF = 2.01  # the room: x, y in [-HALF, HALF] (off the 2 cm cells' edges)
PILLAR = ((0.91, 1.01), (1.21, 1.51))  # a box standing in the room (x range, y range)


def _camera(x: float, y: float, heading_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    h, p = math.radians(heading_deg), math.radians(pitch_deg)
    fwd = np.array([math.cos(h) * math.cos(p), math.sin(h) * math.cos(p), -math.sin(p)])
    down = np.array([-math.cos(h) * math.sin(p), -math.sin(h) * math.sin(p), -math.cos(p)])
    right = np.cross(down, fwd)
    t = np.eye(4)
    t[:3, 0], t[:3, 1], t[:3, 2], t[:3, 3] = right, down, fwd, [x, y, EYE]
    return t


def _intrinsics() -> np.ndarray:
    f = (SIZE / 2) / math.tan(math.radians(45.0))
    return np.array([[f, 0, (SIZE - 1) / 2], [0, f, (SIZE - 1) / 2], [0, 0, 1.0]])


def _depth(cam: np.ndarray, room: bool = True) -> np.ndarray:
    """Depth along the optical axis of the walls, the pillar and the floor, seen from ``cam``
    (``room`` False: the floor alone, as in a hall wider than the depth sensor reaches)."""
    k = _intrinsics()
    v, u = np.mgrid[0:SIZE, 0:SIZE]
    rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u, float)], -1)
    d = rays.reshape(-1, 3) @ cam[:3, :3].T  # world directions, optical z = 1
    o = cam[:3, 3]
    best = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in (0, 1) if room else ():
            for wall in (-HALF, HALF):
                t = (wall - o[axis]) / d[:, axis]
                best = np.where((t > 0) & (t < best), t, best)
        t = -o[2] / d[:, 2]  # the floor
        best = np.where((t > 0) & (t < best), t, best)
        (x0, x1), (y0, y1) = PILLAR  # slab test
        tx = np.sort(np.stack([(x0 - o[0]) / d[:, 0], (x1 - o[0]) / d[:, 0]]), axis=0)
        ty = np.sort(np.stack([(y0 - o[1]) / d[:, 1], (y1 - o[1]) / d[:, 1]]), axis=0)
        near, far = np.maximum(tx[0], ty[0]), np.minimum(tx[1], ty[1])
        hit = (near < far) & (near > 0) & (near < best) & room
    best = np.where(hit, near, best)
    return best.reshape(SIZE, SIZE).astype(np.float32)


def _obs(
    true: tuple[float, float, float],
    reported: tuple[float, float, float],
    pitch: float = 0.0,
    room: bool = True,
) -> Observation:
    return Observation(
        session="t",
        step=1,
        rgb=np.zeros((SIZE, SIZE, 3), np.uint8),
        depth=_depth(_camera(*true, pitch), room),
        camera_pose=_camera(*reported, pitch),
        agent_pose=(reported[0], reported[1], reported[2], pitch),
        intrinsics=_intrinsics(),
    )


@pytest.fixture
def grid() -> GridSpec:
    cfg = MapConfig()
    half = cfg.map_size_m / 2
    return GridSpec((-half, -half), cfg.nav_cell, cfg.nav_shape)


def _localiser(grid: GridSpec) -> ScanLocaliser:
    """A localiser that has mapped the room from ``SPOT`` with exact poses (a look around)."""
    cfg = MapConfig()
    loc = ScanLocaliser(grid, cfg.obstacle_z, cfg.max_depth)
    for heading in (0.0, 90.0, 180.0, -90.0):
        pose = (*SPOT, heading)
        assert loc.correct(_obs(pose, pose)).agent_pose == (*pose, 0.0)
    assert loc.applied == 0  # exact poses: nothing to correct
    return loc


SPOT = (-1.0, -0.8)


def test_a_drifted_pose_is_pulled_back_onto_the_map(grid: GridSpec) -> None:
    true = (-0.9, -0.7, 35.0)
    reported = (-0.87, -0.73, 36.2)  # 1.2 deg and 4 cm off, as a few noisy steps leave it
    loc = _localiser(grid)
    got = loc.correct(_obs(true, reported))
    x, y, heading, _ = got.agent_pose
    assert loc.applied == 1
    # within the search's steps (0.25 deg, 1.25 cm) and the map's 2 cm cells
    assert abs(heading - true[2]) < 0.3
    assert math.hypot(x - true[0], y - true[1]) < 0.02
    # the camera pose moved with it: the corrected camera sits over the corrected agent
    assert np.allclose(got.camera_pose[:2, 3], [x, y])
    assert np.allclose(got.camera_pose[:3, :3], _camera(*true)[:3, :3], atol=np.radians(0.3))
    # the correction holds for the next frames: the same drift is not corrected twice
    again = loc.correct(_obs(true, reported))
    assert math.hypot(again.agent_pose[0] - true[0], again.agent_pose[1] - true[1]) < 0.02


def test_the_true_pose_stays(grid: GridSpec) -> None:
    true = (-0.5, 0.4, -60.0)
    loc = _localiser(grid)
    got = loc.correct(_obs(true, true))
    x, y, heading, _ = got.agent_pose  # at most a cell's wobble: the map's points are on 2 cm cells
    assert math.hypot(x - true[0], y - true[1]) <= 0.0125 and abs(heading - true[2]) <= 0.25


def test_no_correction_without_a_map_or_without_walls_in_view(grid: GridSpec) -> None:
    true, reported = (-0.9, -0.7, 35.0), (-0.87, -0.73, 36.2)
    cfg = MapConfig()
    fresh = ScanLocaliser(grid, cfg.obstacle_z, cfg.max_depth)
    assert fresh.correct(_obs(true, reported)).agent_pose == (*reported, 0.0)  # nothing mapped yet
    loc = _localiser(grid)
    loc.correct(_obs(true, reported, pitch=30.0, room=False))  # the floor alone: nothing to lay on the map
    assert fresh.applied == 0 and loc.applied == 0
    assert loc.correction.turn == 0.0 and not loc.correction.shift.any()


def test_a_new_phase_starts_uncorrected_on_the_old_map(grid: GridSpec) -> None:
    loc = _localiser(grid)
    loc.correct(_obs((-0.9, -0.7, 35.0), (-0.87, -0.73, 36.2)))
    assert loc.applied == 1
    loc.new_phase()  # back at the true start pose
    assert loc.correction.turn == 0.0 and not loc.correction.shift.any()
    # the walkthrough's map still places a drifted frame of the next phase
    got = loc.correct(_obs((-0.9, -0.7, 35.0), (-0.87, -0.73, 36.2)))
    assert loc.applied == 2 and math.hypot(got.agent_pose[0] + 0.9, got.agent_pose[1] + 0.7) < 0.02


def test_corrections_compose() -> None:
    c = Correction().then(math.radians(90.0), np.array([1.0, 0.0]), np.array([0.0, 0.5]))
    # a turn by 90 deg about (1, 0) takes (2, 0) to (1, 1); then the shift
    assert np.allclose(c.apply_xy(np.array([2.0, 0.0])), [1.0, 1.5])
    assert np.allclose(c.matrix()[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    assert np.allclose(c.matrix()[:2, 3], c.apply_xy(np.zeros(2)))


def test_when_the_agent_localises() -> None:
    assert wants_localiser("auto", pose_noise=True) and not wants_localiser("auto", pose_noise=False)
    assert wants_localiser("scan", pose_noise=False) and not wants_localiser("off", pose_noise=True)
    with pytest.raises(ValueError, match="localise must be one of"):
        AgentConfig(localise="gps")  # type: ignore[arg-type]
