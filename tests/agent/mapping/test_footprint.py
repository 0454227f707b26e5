"""A small object's footprint (long axis, colour) from the points of one view, pooled over views."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tidee.agent.mapping.footprint import (
    NEAR_SIDE_M,
    Footprint,
    FootprintVotes,
    axis_gap,
    footprint,
    outline_axis,
    weighted_median,
)


def turn(heading_deg: float) -> np.ndarray:
    """The 2x2 rotation by ``heading_deg`` degrees (x, y)."""
    t = math.radians(heading_deg)
    return np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])


def box_view(
    centre: tuple[float, float],
    size: tuple[float, float, float],
    heading_deg: float,
    table_z: float = 0.75,
    surround: float = 0.06,
    step: float = 0.004,
    corner: bool = False,
) -> np.ndarray:
    """Points a camera sees of a box on a table: its top face, the side facing the camera (its
    -y side; ``corner``: its -x side too, a camera looking at a corner) and the table around it
    (a depth-cut box mask)."""
    sx, sy, sz = size
    rot = turn(heading_deg)
    pts = []
    for lx in np.arange(-sx / 2, sx / 2 + 1e-9, step):
        for ly in np.arange(-sy / 2, sy / 2 + 1e-9, step):
            pts.append((lx, ly, table_z + sz))
        for lz in np.arange(0.0, sz, step):
            pts.append((lx, -sy / 2, table_z + lz))
    for ly in np.arange(-sy / 2, sy / 2 + 1e-9, step) if corner else ():
        for lz in np.arange(0.0, sz, step):
            pts.append((-sx / 2, ly, table_z + lz))
    out = np.array(pts)
    out[:, :2] = out[:, :2] @ rot.T + centre
    gx = np.arange(-sx / 2 - surround, sx / 2 + surround, step)
    gy = np.arange(-sy / 2 - surround, sy / 2 + surround, step)
    ring = np.array([(x, y) for x in gx for y in gy if max(abs(x) - sx / 2, abs(y) - sy / 2) > 0.0])
    if not len(ring):
        return out
    table = np.column_stack([ring @ rot.T + centre, np.full(len(ring), table_z)])
    return np.vstack([out, table])


@pytest.mark.parametrize("heading", [0.0, 30.0, 100.0, 165.0])
def test_a_long_box_gives_its_heading_not_the_table_around_it(heading: float) -> None:
    fp = footprint(box_view((1.2, -0.4), (0.16, 0.05, 0.03), heading))
    assert fp is not None
    assert abs(axis_gap(fp.axis_deg, heading % 180.0)) < 3.0
    assert fp.elongation > 0.5


def test_a_tall_box_seen_at_a_corner_lies_along_its_top_face() -> None:
    # 14 x 7 cm, 25 cm tall: its two sides a camera sees at a corner have far more points than
    # its top, and pull the points' long axis round towards the corner's diagonal
    pts = box_view((0.0, 0.0), (0.14, 0.07, 0.25), 30.0, surround=0.0, corner=True)
    fp = footprint(pts)
    assert fp is not None and abs(axis_gap(fp.axis_deg, 30.0)) < 3.0
    sides_too = footprint(pts, top_band=10.0)  # the sides' points count too
    assert sides_too is not None and abs(axis_gap(sides_too.axis_deg, 30.0)) > 10.0


def test_the_colour_is_that_of_the_object_not_its_support() -> None:
    pts = box_view((0.0, 0.0), (0.10, 0.05, 0.04), 0.0)
    rgb = np.where((pts[:, 2] > 0.751)[:, None], [200, 20, 20], [90, 90, 90])  # a red box on grey
    fp = footprint(pts, rgb)
    assert fp is not None and fp.colour is not None
    assert np.allclose(fp.colour, np.array([200, 20, 20]) / 255)


def test_a_flat_thing_is_all_points_and_too_few_points_are_nothing() -> None:
    flat = box_view((0.5, 0.5), (0.12, 0.04, 0.002), 45.0, surround=0.0)
    fp = footprint(flat)
    assert fp is not None and abs(axis_gap(fp.axis_deg, 45.0)) < 3.0
    assert footprint(flat[:5]) is None


def test_votes_pool_views_by_their_points_and_axes_by_elongation_too() -> None:
    v = FootprintVotes()
    assert v.axis_deg() is None and v.colour is None
    v.add(Footprint(178.0, 0.8, 300, np.array([0.9, 0.1, 0.1])))  # near view: 178 and 4 degrees are one axis
    v.add(Footprint(4.0, 0.8, 100, np.array([0.5, 0.1, 0.1])))
    v.add(Footprint(90.0, 0.0, 200))  # a view where it looked square: no say in the axis, none in colour
    axis = v.axis_deg()
    assert axis is not None and abs(axis_gap(axis, 179.5)) < 0.6
    assert np.allclose(v.colour, [0.8, 0.1, 0.1])  # (300 x 0.9 + 100 x 0.5) / 400


def test_no_axis_when_the_views_disagree_or_the_thing_is_round() -> None:
    split = FootprintVotes()
    split.add(Footprint(0.0, 0.9, 100))
    split.add(Footprint(90.0, 0.9, 100))
    assert split.axis_deg() is None
    round_ = FootprintVotes()
    round_.add(Footprint(33.0, 0.05, 500))
    assert round_.axis_deg() is None


def test_a_heading_guess_takes_what_the_views_lean_to_where_no_axis_is_sure() -> None:
    weak = FootprintVotes()  # a towel seen at a grazing angle: a little longer than wide
    weak.add(Footprint(33.0, 0.05, 500))
    weak.add(Footprint(40.0, 0.1, 100))
    assert weak.axis_deg() is None
    guess = weak.heading_guess()
    assert guess is not None and 33.0 < guess < 40.0
    sure = FootprintVotes()
    sure.add(Footprint(120.0, 0.8, 100))
    assert sure.heading_guess() == pytest.approx(sure.axis_deg())
    square = FootprintVotes()  # no view showed any spread: no guess
    square.add(Footprint(0.0, 0.0, 100))
    assert square.heading_guess() is None


@pytest.mark.parametrize("heading", [0.0, 30.0, 100.0])
def test_a_views_middle_is_that_of_the_top_face_not_of_the_side_or_the_table(heading: float) -> None:
    # the side facing the camera and the table around it lie off to one side or all round; the
    # top face's trimmed extent is centred on the box
    fp = footprint(box_view((1.2, -0.4), (0.16, 0.05, 0.03), heading))
    assert fp is not None and fp.middle is not None
    assert np.allclose(fp.middle, (1.2, -0.4), atol=0.005)  # the points lie on a 4 mm grid
    # a view that sees only part of the top (the mask cut 4 cm off its +x end): its middle moves 2 cm
    pts = box_view((0.0, 0.0), (0.16, 0.05, 0.03), 0.0, surround=0.0)
    part = footprint(pts[pts[:, 0] <= 0.04])
    assert part is not None and part.middle is not None
    assert np.allclose(part.middle, (-0.02, 0.0), atol=0.004)


def laptop_view(from_front: bool, heading_deg: float, table: bool = False, step: float = 0.004) -> np.ndarray:
    """Points a camera sees of an open laptop (0.33 x 0.23 m, centred at (0.5, 0.2) on a table
    at 0.75 m): from the front, its base's top (2 cm high) and its upright lid's front face
    (2 cm thick, along the back edge, 20 cm tall); from behind, the lid's back face only;
    ``table``: and the table 6 cm round it (a depth-cut box mask)."""
    sx, sy = 0.33, 0.23
    pts = []
    if table:
        for lx in np.arange(-sx / 2 - 0.06, sx / 2 + 0.06, step):
            for ly in np.arange(-sy / 2 - 0.06, sy / 2 + 0.06, step):
                if abs(lx) > sx / 2 or abs(ly) > sy / 2:
                    pts.append((lx, ly, 0.75))
    for lx in np.arange(-sx / 2, sx / 2 + 1e-9, step):
        if from_front:
            for ly in np.arange(-sy / 2 + 0.02, sy / 2 + 1e-9, step):
                pts.append((lx, ly, 0.77))
        for lz in np.arange(0.0, 0.2, step):
            pts.append((lx, -sy / 2 + (0.02 if from_front else 0.0), 0.77 + lz))
        for ly in np.arange(-sy / 2, -sy / 2 + 0.02 + 1e-9, step):  # the lid's top edge
            pts.append((lx, ly, 0.97))
    out = np.array(pts)
    rot = turn(heading_deg)
    out[:, :2] = out[:, :2] @ rot.T + (0.5, 0.2)
    return out


@pytest.mark.parametrize("heading", [0.0, 40.0, 115.0])
def test_a_view_whose_top_is_an_edge_along_one_side_takes_the_middle_of_the_body(heading: float) -> None:
    # from the front, the laptop's highest points are its lid's top edge, 10.5 cm behind its
    # centre; the base in front of the lid says where the laptop is
    # with the table in the mask, the points above it are the body; without, the lift takes the
    # base for the support, and all the points are
    for table in (False, True):
        front = footprint(laptop_view(True, heading, table))
        assert front is not None and front.middle is not None
        assert np.linalg.norm(np.subtract(front.middle, (0.5, 0.2))) < 0.015
        assert abs(axis_gap(front.axis_deg, heading % 180.0)) < 3.0  # the lid's edge still gives the axis
    # from behind only the lid shows: no body beside the edge, the middle stays the lid's
    back = footprint(laptop_view(False, heading))
    assert back is not None and back.middle is not None
    lid = np.array([0.5, 0.2]) - 0.105 * turn(heading)[:, 1]  # 10.5 cm behind, along the laptop's -y
    assert np.linalg.norm(np.subtract(back.middle, lid)) < 0.015


def test_weighted_median_is_where_half_the_weight_is_reached() -> None:
    assert (
        weighted_median(np.array([0.3, 0.1, 0.2]), np.array([150.0, 100.0, 100.0])) == 0.2
    )  # 100, 200 >= 175
    assert weighted_median(np.array([0.3, 0.1, 0.2]), np.array([400.0, 100.0, 100.0])) == 0.3
    assert weighted_median(np.array([5.0]), np.array([1.0])) == 5.0


def test_votes_give_the_weighted_median_of_the_views_middles() -> None:
    v = FootprintVotes()
    assert v.middle() is None
    v.add(Footprint(0.0, 0.8, 300, middle=(0.10, 0.00)))  # a near view
    v.add(Footprint(0.0, 0.8, 100, middle=(0.12, 0.05)))
    v.add(Footprint(0.0, 0.8, 150, middle=(0.50, -0.30)))  # a bad mask, far off: no pull
    v.add(Footprint(0.0, 0.8, 900))  # no middle: no say in it
    # x: 0.10 (300) already reaches half of 550; y: -0.30 (150), 0.00 (450) reaches it
    assert v.middle() == (0.10, 0.0)
    v.add(Footprint(0.0, 0.8, 400, middle=(0.12, 0.05)))  # now 0.12 / 0.05 hold most of the weight
    assert v.middle() == (0.12, 0.05)


def test_votes_with_eyes_meet_where_the_views_rays_cross() -> None:
    # an object at (1, 0): seen along x from (0, 0) and along y from (1, -1), each view's middle
    # 3 cm short of it (the near side); a third view's bad mask lies 20 cm off its own ray
    v = FootprintVotes()
    v.add(Footprint(0.0, 0.8, 200, middle=(0.97, 0.0)), eye=(0.0, 0.0))
    v.add(Footprint(0.0, 0.8, 200, middle=(1.0, -0.03)), eye=(1.0, -1.0))
    v.add(Footprint(0.0, 0.8, 100, middle=(1.0, 0.2)), eye=(2.0, 0.2))
    x, y = v.middle()  # type: ignore[misc]
    # the rays cross at (1, 0); the bad view, its weight cut tenfold (20 cm / RAY_SLACK_M), pulls
    # y by under a centimetre
    assert abs(x - 1.0) < 0.004 and abs(y) < 0.01
    # every view from one side: the middle moved NEAR_SIDE_M further along the ray, no more
    one_way = FootprintVotes()
    one_way.add(Footprint(0.0, 0.8, 200, middle=(0.97, 0.0)), eye=(0.0, 0.0))
    one_way.add(Footprint(0.0, 0.8, 100, middle=(0.97, 0.0)), eye=(-0.5, 0.0))
    assert one_way.middle() == pytest.approx((0.97 + NEAR_SIDE_M, 0.0))


@pytest.mark.parametrize(
    "a, b, turn", [(10.0, 0.0, 10.0), (0.0, 170.0, 10.0), (170.0, 0.0, -10.0), (90.0, 0.0, -90.0)]
)
def test_axis_gap_is_the_shortest_turn_between_two_axes(a: float, b: float, turn: float) -> None:
    assert axis_gap(a, b) == pytest.approx(turn)


def side_view(
    centre: tuple[float, float],
    size: tuple[float, float, float],
    heading_deg: float,
    eye: tuple[float, float, float],
    base_z: float = 0.92,
    step: float = 0.004,
) -> np.ndarray:
    """Points a camera below a box's top sees of it: the sides that face the eye, no top (a box
    on a kitchen counter, 0.92 m, seen from the agent's 0.9 m eye)."""
    sx, sy, sz = size
    rot = turn(heading_deg)
    pts = []
    faces = (((1, 0), sx / 2, sy), ((-1, 0), sx / 2, sy), ((0, 1), sy / 2, sx), ((0, -1), sy / 2, sx))
    for normal, half, length in faces:
        n = rot @ np.array(normal, float)
        mid = np.array(centre) + n * half
        if n @ (np.array(eye[:2]) - mid) <= 0:
            continue  # faces away from the eye
        along = np.array([-n[1], n[0]])
        for s_ in np.arange(-length / 2, length / 2 + 1e-9, step):
            for z in np.arange(base_z, base_z + sz, step):
                pts.append((*(mid + s_ * along), z))
    return np.array(pts)


def test_a_view_from_below_the_top_keeps_an_outline_and_one_from_above_does_not() -> None:
    box = box_view((1.0, 0.0), (0.16, 0.05, 0.03), 20.0)  # on a 0.75 m table, top at 0.78
    above = footprint(box, eye=np.array([0.0, 0.0, 0.9]))  # 12 cm over the top, 1 m away: 7 degrees
    assert above is not None and above.outline is None
    level = footprint(box, eye=np.array([0.0, 0.0, 0.85]))  # 7 cm over, 1 m away: 4 degrees
    assert level is not None and level.outline is not None
    assert len(level.outline) <= 128 and level.outline.shape[1] == 2
    assert footprint(box).outline is None  # no eye given: no outline


@pytest.mark.parametrize("heading", [0.0, 30.0, 125.0])
def test_the_rectangle_around_an_outline_lies_along_the_long_side(heading: float) -> None:
    rot = turn(heading)
    # two sides of a 22 x 11 cm box (an L, as one view of a corner shows): 56 + 28 points
    xs = np.linspace(-0.11, 0.11, 56)
    ys = np.linspace(-0.055, 0.055, 28)
    long_side = np.column_stack([xs, np.full_like(xs, -0.055)])
    ell = np.vstack([long_side, np.column_stack([np.full_like(ys, 0.11), ys])])
    fit = outline_axis(ell @ rot.T + (2.0, -1.0))
    assert fit is not None
    assert abs(axis_gap(fit[0], heading % 180.0)) <= 1.0
    assert fit[1] == pytest.approx(0.5, abs=0.05)
    assert outline_axis(ell[:5]) is None


def test_an_end_on_view_below_the_top_does_not_turn_the_axis_across() -> None:
    # a 22 x 11 x 8 cm tissue box on a counter (top 1.0 m, above the 0.9 m eye), its long axis
    # at 0 degrees: three views from the long side and one close, end-on view of its short end,
    # which alone has more points than the other three together and whose one side is a line
    # across the long axis
    size, centre = (0.22, 0.11, 0.08), (1.0, -1.3)
    eyes = [(0.3, -0.3, 0.9), (1.0, -0.2, 0.9), (1.7, -0.4, 0.9)]
    views = [side_view(centre, size, 0.0, e, step=0.008) for e in eyes]
    end_on = (1.6, -1.3, 0.9)
    views.append(side_view(centre, size, 0.0, end_on, step=0.003))
    eyes.append(end_on)
    fps = [footprint(v, eye=np.array(e)) for v, e in zip(views, eyes)]
    assert all(fp is not None and fp.outline is not None for fp in fps)
    assert fps[-1].n > sum(fp.n for fp in fps[:-1])
    assert abs(axis_gap(fps[-1].axis_deg, 90.0)) < 3.0  # the end alone: across the long axis
    # pooled by their axes (as views that saw the top are), the end-on view turns it across
    old = FootprintVotes()
    for fp in fps:
        old.add(Footprint(fp.axis_deg, fp.elongation, fp.n))
    assert abs(axis_gap(old.heading_guess(), 90.0)) < 30.0
    votes = FootprintVotes()
    for fp, e in zip(fps, eyes):
        votes.add(fp, e[:2])
    axis = votes.axis_deg()
    assert axis is not None and abs(axis_gap(axis, 0.0)) <= 2.0


def test_views_that_saw_the_top_decide_the_axis_over_side_views() -> None:
    line = np.column_stack([np.full(50, 0.3), np.linspace(0.0, 0.1, 50)])  # one side, along y
    v = FootprintVotes()
    v.add(Footprint(90.0, 1.0, 500, outline=line))
    v.add(Footprint(10.0, 0.6, 40))  # one view of its top
    axis = v.axis_deg()
    assert axis is not None and axis == pytest.approx(10.0)
    sides = FootprintVotes()
    sides.add(Footprint(90.0, 1.0, 500, outline=line))
    axis = sides.axis_deg()
    assert axis is not None and abs(axis_gap(axis, 90.0)) <= 1.0  # one side, a line: all it can say
    square = FootprintVotes()  # a square's outline: no axis, and a guess all the same
    edge = np.linspace(0.0, 0.1, 20)
    ring = np.array([(x, y) for x in edge for y in (0.0, 0.1)] + [(x, y) for y in edge for x in (0.0, 0.1)])
    square.add(Footprint(0.0, 0.0, 80, outline=ring))
    assert square.axis_deg() is None and square.heading_guess() is not None
