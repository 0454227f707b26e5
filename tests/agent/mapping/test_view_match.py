"""match_view: where an object lies now against an earlier view from the same pose, on frames
ray-cast here (a two-coloured box on a floor) so that the true move is known."""

import math

import numpy as np
import pytest

from tidee.agent.mapping.view_match import FrameCrop, ObjectView, foreground, match_view, turned

SIZE = 256
FOCAL = SIZE / 2  # 90 degrees across
EYE = np.array([0.0, 0.0, 0.9])
BOX = np.array([0.12, 0.05, 0.04])  # length, width, height (m)


def camera(pitch_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics and camera-to-start pose of a camera at ``EYE`` facing +x, tilted down."""
    p = math.radians(pitch_deg)
    fwd = np.array([math.cos(p), 0.0, -math.sin(p)])
    right = np.array([0.0, -1.0, 0.0])
    down = np.cross(fwd, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, fwd, EYE
    k = np.array([[FOCAL, 0.0, (SIZE - 1) / 2], [0.0, FOCAL, (SIZE - 1) / 2], [0.0, 0.0, 1.0]])
    return k, pose


def view_of(rgb, depth, k, pose, region, agent_pose):
    crop = FrameCrop.of(rgb, depth, k, pose, region, agent_pose)
    return None if crop is None else crop.view()


def render(k: np.ndarray, pose: np.ndarray, xy: tuple[float, float], yaw_deg: float):
    """RGB, depth (along the optical axis) and the object's pixels: a box lying at ``xy``
    turned by ``yaw_deg``, red at one end and blue at the other, on a brown floor at z = 0."""
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    rays = np.stack([(u - k[0, 2]) / FOCAL, (v - k[1, 2]) / FOCAL, np.ones_like(u)], axis=-1) @ pose[:3, :3].T
    t_floor = np.where(rays[..., 2] < 0, -EYE[2] / np.minimum(rays[..., 2], -1e-9), np.inf)
    # the ray in the box's frame, then the slab test
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world to box
    origin = rot @ (EYE - np.array([xy[0], xy[1], BOX[2] / 2]))
    d = rays @ rot.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-BOX / 2 - origin) / d
        t2 = (BOX / 2 - origin) / d
    near = np.nanmax(np.minimum(t1, t2), axis=-1)
    far = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit = (near <= far) & (near > 0)
    t = np.where(hit, near, t_floor)
    along = origin[0] + t * d[..., 0]  # where on the box's length the ray meets it
    rgb = np.empty((SIZE, SIZE, 3), np.uint8)
    rgb[:] = (170, 130, 80)
    rgb[hit & (along >= 0)] = (200, 40, 40)
    rgb[hit & (along < 0)] = (40, 60, 200)
    return rgb, t.astype(np.float32), hit


@pytest.mark.parametrize("pitch", [30.0, 60.0])
def test_match_view_finds_the_move_and_the_turn(pitch):
    k, pose = camera(pitch)
    place = (0.8, 0.05) if pitch == 30.0 else (0.6, -0.05)
    rgb, depth, hit = render(k, pose, place, 30.0)
    view = view_of(rgb, depth, k, pose, hit, (0.0, 0.0, 0.0, pitch))
    assert view is not None and len(view.points) > 50
    moved = (place[0] + 0.035, place[1] - 0.02)
    rgb2, depth2, _ = render(k, pose, moved, 30.0 + 25.0)
    match = match_view(view, rgb2, depth2, k, pose)
    assert match.turn_deg == pytest.approx(25.0, abs=3.0)
    # the box's centre as the view saw it, carried by the match, lands on where it is now
    now = match.moved_to(view.centre, np.array(place))
    assert np.linalg.norm(now - np.array(moved)) < 0.006
    assert match.still_misfit - match.misfit > 0.2
    assert match.seen > 0.9


def test_match_view_of_an_unmoved_object_is_still():
    k, pose = camera(45.0)
    rgb, depth, hit = render(k, pose, (0.9, 0.0), -10.0)
    view = view_of(rgb, depth, k, pose, hit, (0.0, 0.0, 0.0, 45.0))
    match = match_view(view, rgb, depth, k, pose)
    assert np.linalg.norm(match.shift) < 1e-9 and match.turn_deg == 0.0
    assert match.misfit < 1e-6 and match.still_misfit < 1e-6


def test_a_turned_half_round_box_is_told_from_one_not_turned():
    """The two-coloured ends tell 180 degrees from none."""
    k, pose = camera(60.0)
    rgb, depth, hit = render(k, pose, (0.6, 0.0), 0.0)
    view = view_of(rgb, depth, k, pose, hit, (0.0, 0.0, 0.0, 60.0))
    rgb2, depth2, _ = render(k, pose, (0.6, 0.0), 180.0)
    match = match_view(view, rgb2, depth2, k, pose)
    assert abs(abs(match.turn_deg) - 180.0) <= 3.0


def test_within_keeps_the_points_of_the_box_above_its_base():
    pts = np.array([[0.9, 0.0, 0.02], [0.9, 0.0, 0.001], [0.95, 0.1, 0.02], [0.95, 0.0, 0.03]])
    view = ObjectView((0.0, 0.0, 0.0, 45.0), pts, np.zeros((4, 3), np.float32))
    kept = view.within(np.array([0.84, -0.025, 0.0]), np.array([0.96, 0.025, 0.04]), 0.01, 0.005)
    assert kept.points.tolist() == [pts[0].tolist(), pts[3].tolist()]


def test_a_views_points_are_the_objects_not_the_floor_round_it():
    """A box mask of a box turned 30 degrees holds floor in its corners: the view keeps
    the pixels coloured unlike the rim of the box, the object's."""
    k, pose = camera(60.0)
    rgb, depth, hit = render(k, pose, (0.6, 0.0), 30.0)
    rows, cols = np.nonzero(hit)
    box = np.zeros_like(hit)
    box[rows.min() - 2 : rows.max() + 3, cols.min() - 2 : cols.max() + 3] = True
    assert foreground(rgb, box).tolist() == hit.tolist()
    view = view_of(rgb, depth, k, pose, box, (0.0, 0.0, 0.0, 60.0))
    assert view is not None and view.points[:, 2].min() > 0.0
    # an object that fills its box: the box is kept
    assert foreground(rgb, hit).tolist() == hit.tolist()


def test_turned_is_counter_clockwise():
    assert turned(np.array([[1.0, 0.0]]), 90.0) == pytest.approx(np.array([[0.0, 1.0]]))


def test_moved_from_undoes_moved_to():
    """A put aimed at where the match says the view's place went to lands it on the place."""
    from tidee.agent.mapping.view_match import ViewMatch

    match = ViewMatch(np.array([0.03, -0.02]), 35.0, 0.1, 0.5, 1.0)
    centre, place = np.array([1.0, 2.0]), np.array([1.02, 1.99])
    now = match.moved_to(centre, place)
    assert np.linalg.norm(now - place) > 0.02
    assert match.moved_from(centre, now) == pytest.approx(place)


def test_a_frame_crop_makes_the_same_view_as_its_frame():
    k, pose = camera(45.0)
    rgb, depth, hit = render(k, pose, (0.9, 0.1), 20.0)
    crop = FrameCrop.of(rgb, depth, k, pose, hit, (0.0, 0.0, 0.0, 45.0))
    assert crop is not None and crop.rgb.shape[0] < SIZE / 4
    whole = FrameCrop((0.0, 0.0, 0.0, 45.0), rgb, depth, hit, k, pose).view()
    assert crop.view().points == pytest.approx(whole.points)
