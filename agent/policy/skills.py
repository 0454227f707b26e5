"""The agent's motor skills, as generators that yield actions (paper §3.1, supplement).

Each skill is a generator: it yields an ``Action``; by the time it resumes, the runner has
stepped the world and folded the new observation into the maps (``body.obs`` and
``body.detections`` are current). A skill's return value (``yield from``) says whether it
worked. Skills only use the agent's own maps and detections, never ground truth.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from tidee.agent.classes import PICKUPABLE
from tidee.agent.mapping.geometry import project, unproject
from tidee.agent.mapping.maps import SemanticMapper
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.navigation.explore import FrontierExplorer
from tidee.agent.navigation.fmm import FMMPlanner, NavStatus, wrap_deg
from tidee.agent.perception.base import Detection
from tidee.protocol.messages import Action, ActionName, Observation

Skill = Generator[Action, None, bool]
AGENT_RADIUS = 0.2  # metres (the server's collision radius)
PITCHES = (-30.0, 0.0, 30.0, 60.0)
MOVE_M = 0.25
RETRY_AWAY_M = 0.5  # a retried approach stands at least this far from the spots already tried, metres
EDGE_MARGIN = 0.05  # share of the frame's width / height at each border that a put never aims at
AIM_MIN_SHARE = 0.2  # other receptacles' pixels are avoided only while this share of the target's remains


@dataclass
class Body:
    """What the skills read and write: the latest observation, the maps, the plan for display."""

    mapper: SemanticMapper
    obs: Observation | None = None
    detections: list[Detection] = field(default_factory=list)
    path: np.ndarray | None = None  # float32 Mx2: the current planned path (viewer)
    goal: tuple[float, float] | None = None
    nav_steps: int = 0

    @property
    def pose(self) -> tuple[float, float, float, float]:
        assert self.obs is not None
        return tuple(float(v) for v in self.obs.agent_pose)  # type: ignore[return-value]

    @property
    def xy(self) -> np.ndarray:
        x, y, _, _ = self.pose
        return np.array([x, y])

    def steps_left(self) -> int:
        return int(self.obs.steps_left) if self.obs is not None else 0


# --- navigation ---------------------------------------------------------------------------


def footprint_gap(box_min: np.ndarray, box_max: np.ndarray, x, y):
    """Metres from points (x, y) (scalars or broadcasting arrays) to a box's (x, y) footprint;
    0 inside it."""
    dx = np.maximum(np.maximum(box_min[0] - x, x - box_max[0]), 0.0)
    dy = np.maximum(np.maximum(box_min[1] - y, y - box_max[1]), 0.0)
    return np.hypot(dx, dy)


def goal_mask_near_box(
    mapper: SemanticMapper, box_min: np.ndarray, box_max: np.ndarray, radius: float
) -> np.ndarray:
    """bool grid: cells whose centre is within ``radius`` of the box's (x, y) footprint."""
    x, y = mapper.grid.centres()
    return footprint_gap(box_min, box_max, x, y) <= radius


def mask_away_from(
    mask: np.ndarray,
    grid,
    tried_xy: list[np.ndarray] | list[tuple[float, float]],
    min_m: float = RETRY_AWAY_M,
) -> np.ndarray:
    """``mask`` (bool nav grid) without the cells whose centre is within ``min_m`` of one of
    the (x, y) positions ``tried_xy``: the goal region of a retry from another side of a
    target, after the spots already tried saw nothing or could not reach it. Empty when every
    cell is near a tried spot (the caller decides whether to fall back on ``mask``)."""
    if not len(tried_xy):
        return mask.copy()
    x, y = grid.centres()
    near = np.zeros(mask.shape, bool)
    for p in tried_xy:
        near |= np.hypot(x - float(p[0]), y - float(p[1])) < min_m
    return mask & ~near


STUCK_TURNS = 4  # 90-degree turns on the spot before a stuck walk gives up
ON_THE_SPOT = 8  # actions without a move before any walk gives up (a plan turns twice at most)
TRAPPED_CELLS = 20  # a start component this small (0.05 m² at 5 cm cells): the agent is hemmed in


def planner_and_reach(body: Body) -> tuple[FMMPlanner, np.ndarray]:
    """A planner on ``traversible(AGENT_RADIUS)`` and the cells it reaches from the agent
    (unknown counts as free); when the agent is hemmed in on that map, on
    ``traversible(AGENT_RADIUS / 2)`` until it has stepped clear. Hemmed in: its start
    component is tiny (a start at the foot of a bed: the dilated bed covers every cell around
    it), or none of the four lattice moves stays on traversible cells (an object it just put
    on the floor in front of it, a wall beside and behind it: the start reaches the rest of
    the room only diagonally, which no move can follow). Without it every plan from there
    snapped to the agent's own cell and "arrived" without a move, or turned on the spot as
    "stuck" until the episode ran out."""
    mapper, xy = body.mapper, tuple(body.xy)
    planner = radius_planner(mapper, AGENT_RADIUS)
    reach = planner.reachable_from(xy)
    if int(reach.sum()) < TRAPPED_CELLS or not can_step(planner, xy):
        planner = radius_planner(mapper, AGENT_RADIUS / 2)
        reach = planner.reachable_from(xy)
    return planner, reach


def radius_planner(mapper: SemanticMapper, radius: float) -> FMMPlanner:
    """A planner on the map's cells where the agent's centre may go at ``radius``."""
    return FMMPlanner(mapper.traversible(radius), mapper.grid)


def can_step(planner: FMMPlanner, xy: tuple[float, float]) -> bool:
    """Whether one of the four lattice moves (``MOVE_M`` along ±x or ±y: the agent's headings
    are multiples of 90° in the start frame) from ``xy`` stays on the planner's traversible cells."""
    x, y = xy
    return any(
        planner.segment_free(x, y, x + dx, y + dy)
        for dx, dy in ((MOVE_M, 0.0), (-MOVE_M, 0.0), (0.0, MOVE_M), (0.0, -MOVE_M))
    )


def planner_from(body: Body) -> FMMPlanner:
    return planner_and_reach(body)[0]


def reachable_mask(body: Body) -> np.ndarray:
    """bool nav grid: cells the agent can reach from where it stands (unknown counts as free)."""
    return planner_and_reach(body)[1]


def frontier_goal(
    body: Body, explorer: FrontierExplorer, planner: FMMPlanner | None = None
) -> tuple[float, float] | None:
    """The explorer's next goal from where the agent stands: the geodesically nearest
    frontier (None: none left). ``planner``: one already built for this step."""
    planner = planner or planner_from(body)
    planner.set_goal(tuple(body.xy))
    mapper = body.mapper
    occ = mapper.occupancy_grid()
    return explorer.next_goal(occ == 1, mapper.explored | (occ > 0), mapper.obstacle, planner, tuple(body.xy))


def navigate(
    body: Body,
    goal_xy: tuple[float, float] | None = None,
    goal_mask: np.ndarray | None = None,
    radius: float = 0.0,
    stop_radius: float = 0.2,
    budget: int = 60,
) -> Skill:
    """Walk to a goal with fast-marching planning, replanning every step on the growing map.

    A blocked move stamps an obstacle in front of the agent (the failed cell) and replans.
    Where the map at the agent radius leaves no way the moves can follow, the walk plans at
    half the radius until the agent has moved. Returns True on arrival; False when the goal
    is unreachable, the budget is spent, the agent keeps bumping into things, the planner
    has been stuck (no move lowers the distance: it turns towards downhill) for more than a
    full turn on the spot, or the agent has stood on one spot for ``ON_THE_SPOT`` actions
    (plans that disagree from one step to the next: left, right, left ...).
    """
    bumps = stuck = on_spot = 0
    narrow_at: tuple[float, float] | None = None  # where the half-radius map was needed
    if goal_mask is not None:  # shown to viewers: the centre of the goal region
        body.goal = body.mapper.grid.to_world(np.argwhere(goal_mask).mean(0)) if goal_mask.any() else None
    else:
        assert goal_xy is not None
        body.goal = (float(goal_xy[0]), float(goal_xy[1]))

    def plan(planner: FMMPlanner) -> tuple[bool, ActionName | None]:
        """(goal set, next action) on ``planner`` from the loop's current pose (x, y, yaw)."""
        if goal_mask is not None:
            ok = planner.set_goal_mask(goal_mask, start_xy=(x, y))
        else:
            ok = planner.set_goal(goal_xy, radius_m=radius, start_xy=(x, y))
        return ok, (planner.next_action(x, y, yaw, stop_radius_m=stop_radius) if ok else None)

    for _ in range(budget):
        if body.steps_left() <= 1:
            return False
        x, y, yaw, _ = body.pose
        if narrow_at is not None and math.hypot(x - narrow_at[0], y - narrow_at[1]) > 1e-3:
            narrow_at = None
        planner = None if narrow_at is not None else planner_from(body)
        ok, action = plan(planner) if planner is not None else (False, None)
        if planner is None or (ok and planner.status == NavStatus.stuck):
            # no lattice path on this map (a passage mapped narrower than the agent's radius
            # allows: noisy depth on both sides of a doorway it walked through): half the
            # radius, kept until the agent has moved so that the two maps' plans do not alternate
            narrow = radius_planner(body.mapper, AGENT_RADIUS / 2)
            ok2, action2 = plan(narrow)
            if ok2 and narrow.status in (NavStatus.progress, NavStatus.detour):
                planner, ok, action, narrow_at = narrow, ok2, action2, (x, y)
            elif planner is None:
                narrow_at = None
                planner = planner_from(body)
                ok, action = plan(planner)
        if not ok:
            return False
        if action is None:
            body.path = None
            return planner.status == NavStatus.arrived
        stuck = stuck + 1 if planner.status == NavStatus.stuck else 0
        if stuck > STUCK_TURNS or on_spot >= ON_THE_SPOT:
            body.path = None
            return False
        body.path = planner.path((x, y), max_points=200).astype(np.float32)
        yield Action(action)
        body.nav_steps += 1
        obs = body.obs
        assert obs is not None
        moved = math.hypot(body.pose[0] - x, body.pose[1] - y) > 1e-3
        on_spot = 0 if moved else on_spot + 1
        if action == ActionName.MoveAhead and not obs.success and obs.error == "blocked":
            bumps += 1
            t = math.radians(yaw)
            body.mapper.stamp_obstacle((x + 0.3 * math.cos(t), y + 0.3 * math.sin(t)), radius=0.1)
            if bumps > 6:
                return False
    return False


def rotate_to(body: Body, yaw_target: float) -> Skill:
    """Turn (in 90° steps) to the heading nearest ``yaw_target`` (degrees)."""
    for _ in range(3):
        diff = wrap_deg(yaw_target - body.pose[2])
        if abs(diff) <= 45.0:
            return True
        yield Action(ActionName.RotateLeft if diff > 0 else ActionName.RotateRight)
    return abs(wrap_deg(yaw_target - body.pose[2])) <= 45.0


def pitch_to(body: Body, pitch_target: float) -> Skill:
    target = min(PITCHES, key=lambda p: abs(p - pitch_target))
    for _ in range(4):
        pitch = body.pose[3]
        if abs(pitch - target) < 1.0:
            return True
        yield Action(ActionName.LookDown if pitch < target else ActionName.LookUp)
    return abs(body.pose[3] - target) < 1.0


def face_point(body: Body, point: np.ndarray) -> Skill:
    """Turn and tilt the camera so that the start-frame ``point`` is as central as possible."""
    x, y, _, _ = body.pose
    yield from rotate_to(body, math.degrees(math.atan2(point[1] - y, point[0] - x)))
    assert body.obs is not None
    cam_z = float(body.obs.camera_pose[2, 3])
    horizontal = max(math.hypot(point[0] - x, point[1] - y), 1e-3)
    return (yield from pitch_to(body, math.degrees(math.atan2(cam_z - point[2], horizontal))))


def look_around(body: Body, pitches: tuple[float, ...] = (30.0, 0.0)) -> Skill:
    """Rotate a full turn at each pitch (the paper's initial look-around)."""
    for p in pitches:
        yield from pitch_to(body, p)
        for _ in range(4):
            if body.steps_left() <= 1:
                return False
            yield Action(ActionName.RotateLeft)
    return True


# --- finding things in view -----------------------------------------------------------------


@dataclass
class Sighting:
    """A tracked object seen in the current frame: the detection and the pixel to act on
    (``detection`` None: placed by projecting the tracked centroid, see ``projected_sighting``)."""

    detection: Detection | None
    u: int
    v: int
    distance: float  # eye-to-surface distance along the ray at (u, v), metres
    point: np.ndarray  # start-frame 3D point at (u, v)

    def action(self, name: ActionName, shape: tuple[int, int], yaw: float | None = None) -> Action:
        """``name`` at this pixel (``yaw``: a put's turn of the held object, degrees)."""
        h, w = shape
        return Action(name, x=(self.u + 0.5) / w, y=(self.v + 0.5) / h, yaw=yaw)


def find_in_view(body: Body, obj: TrackedObject, max_pixel_gap: float = 0.15) -> Sighting | None:
    """The current detection of ``obj`` (same label, nearest its projected centroid), if any."""
    obs = body.obs
    assert obs is not None
    h, w = obs.depth.shape
    u, v, z = project(obj.centroid[None, :], obs.intrinsics, obs.camera_pose)
    u0, v0 = float(u[0]), float(v[0])
    best: tuple[float, Detection] | None = None
    for det in body.detections:
        if det.label != obj.label:
            continue
        ys, xs = np.nonzero(det.region((h, w)))
        if len(xs) == 0:
            continue
        gap = float(np.min(np.hypot(xs - u0, ys - v0))) if z[0] > 0 else float("inf")
        if gap <= max_pixel_gap * w and (best is None or gap < best[0]):
            best = (gap, det)
    if best is None:
        return None
    return sighting_of(body, best[1])


def projected_sighting(
    body: Body,
    obj: TrackedObject,
    reach: float = 1.4,
    margin: float = 0.1,
    nearer_tol: float = 0.15,
    farther_tol: float = 0.15,
) -> Sighting | None:
    """``obj`` placed in the frame from the agent's own map, without a detection: its tracked
    centroid projects at least ``margin`` inside the image, within ``reach`` of the camera,
    and the depth at that pixel is at most ``nearer_tol`` nearer (nothing in front of it)
    and at most ``farther_tol`` farther (the ray meets something where the object should
    be, not the wall behind) than the centroid, and no detection of another pickupable class
    covers that pixel (the detector's close view overrules a track that was a confusion: a
    tennis racket tracked as a box). Small objects are often missed by the detector from up
    close; their tracks are not."""
    obs = body.obs
    assert obs is not None
    h, w = obs.depth.shape
    u, v, z = project(obj.centroid[None, :], obs.intrinsics, obs.camera_pose)
    if not z[0] > 0 or not (margin * w <= u[0] < (1 - margin) * w and margin * h <= v[0] < (1 - margin) * h):
        return None
    cam = obs.camera_pose[:3, 3]
    if float(np.linalg.norm(obj.centroid - cam)) > reach:
        return None
    ui, vi = int(u[0]), int(v[0])
    d = float(obs.depth[vi, ui])
    if not -nearer_tol <= d - float(z[0]) <= farther_tol:
        return None
    if _other_pickupable_at(body, obj.label, ui, vi):  # seen up close as another small thing: a confusion
        return None
    pts, _ = unproject(
        obs.depth,
        obs.intrinsics,
        obs.camera_pose,
        mask=np.eye(1, h * w, vi * w + ui, dtype=bool).reshape(h, w),
    )
    if len(pts) == 0:
        return None
    return Sighting(None, ui, vi, float(np.linalg.norm(pts[0] - cam)), pts[0])


def raised_sighting(
    body: Body,
    obj: TrackedObject,
    reach: float = 1.4,
    min_rise: float = 0.004,
    above_top: float = 0.03,
    skip: tuple[int, int] | None = None,
) -> Sighting | None:
    """A second pixel to pick ``obj`` at, after the first hit its support (a pick that reported
    "Floor cannot be picked up": a box's centre or a projected centroid can miss a mug, a key
    ring or a spoon lying flat by a few centimetres). Among the pixels within ``reach`` whose 3D
    point lies over the track's footprint (its box grown by 5 cm, and at least 12 cm around the
    centroid) and no more than ``above_top`` over the track's top (a wall, a stool or a counter
    beside a thing on the floor rises higher than the thing), those at least ``min_rise`` above
    the lowest of them stand on the surface there; the one nearest the centroid across the floor
    is the pixel. None when nothing rises there (a track with no object under it), or when a
    detection of another pickupable class covers that pixel. ``skip``: the pixel (u, v) that
    already failed."""
    obs = body.obs
    assert obs is not None
    w = obs.depth.shape[1]
    pts, index = unproject(obs.depth, obs.intrinsics, obs.camera_pose)
    cam = obs.camera_pose[:3, 3]
    grow = np.maximum(0.05, 0.12 - 0.5 * (obj.box_max[:2] - obj.box_min[:2]))
    lo, hi = obj.box_min[:2] - grow, obj.box_max[:2] + grow
    keep = np.all((pts[:, :2] >= lo) & (pts[:, :2] <= hi), axis=1)
    keep &= np.linalg.norm(pts - cam, axis=1) <= reach
    keep &= pts[:, 2] <= float(obj.box_max[2]) + above_top
    if skip is not None:
        keep &= index != skip[1] * w + skip[0]
    if keep.sum() < 2:
        return None
    pts, index = pts[keep], index[keep]
    rising = np.flatnonzero(pts[:, 2] - pts[:, 2].min() >= min_rise)
    if len(rising) == 0:
        return None
    k = int(rising[np.argmin(np.linalg.norm(pts[rising, :2] - obj.centroid[:2], axis=1))])
    v, u = divmod(int(index[k]), w)
    if _other_pickupable_at(body, obj.label, u, v):
        return None
    return Sighting(None, u, v, float(np.linalg.norm(pts[k] - cam)), pts[k])


def _other_pickupable_at(body: Body, label: str, u: int, v: int) -> bool:
    """A detection of a pickupable class other than ``label`` covers pixel (u, v) of the frame."""
    shape = cast("Observation", body.obs).depth.shape  # called while acting on the latest frame
    return any(d.label != label and d.label in PICKUPABLE and d.region(shape)[v, u] for d in body.detections)


def sighting_of(
    body: Body,
    det: Detection,
    prefer_top: bool = False,
    reach: float = 1.4,
    avoid: list[np.ndarray] | None = None,
    avoid_m: float = 0.4,
    within: tuple[np.ndarray, np.ndarray] | None = None,
    within_m: float = 0.15,
    others: np.ndarray | None = None,
    edge: float = 0.0,
) -> Sighting | None:
    """The pixel of a detection to act on: its region's most central pixel with valid depth.

    ``prefer_top``: for putting things on a receptacle (not in one: a cabinet's top is often
    the counter over it), prefer pixels whose 3D point lies near
    the top of the region's points (the surface something can rest on), within ``reach`` metres.
    ``within``: the receptacle's mapped box (min, max corners); only points inside it grown by
    ``within_m`` count (a detection's box also covers the wall or window behind and above a
    shelf, a counter top above a cabinet), unless none is.
    ``avoid``: 3D points already tried (a put that found no free space or no receptacle there);
    pixels within ``avoid_m`` of them are skipped while others remain, first in the top band,
    then (when the whole top band was tried: a full top board) among the other reachable points,
    again preferring the highest.
    ``others``, ``edge``: pixels not to aim at while the region has others (``aim_region``).
    """
    obs = body.obs
    assert obs is not None
    h, w = obs.depth.shape
    region = det.region((h, w))
    if others is not None or edge > 0:
        region = aim_region(region, others, edge)
    pts, index = unproject(obs.depth, obs.intrinsics, obs.camera_pose, mask=region)
    if len(index) == 0:
        return None
    ys, xs = np.divmod(index, w)
    dist = np.linalg.norm(pts - obs.camera_pose[:3, 3], axis=1)
    weight = np.hypot(xs - xs.mean(), ys - ys.mean())
    inside = far = None  # points within the mapped box; points away from those tried
    if within is not None:
        lo, hi = np.asarray(within[0]) - within_m, np.asarray(within[1]) + within_m
        inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    if avoid:
        far = np.min([np.linalg.norm(pts - a, axis=1) for a in avoid], axis=0) > avoid_m
    if not prefer_top and (within is not None or avoid):  # the body's centre: a door, a drawer front
        keep = np.ones(len(xs), bool)
        if inside is not None and inside.any():
            keep = inside
        if far is not None and (keep & far).any():
            keep = keep & far
        cx, cy = xs[keep].mean(), ys[keep].mean()
        weight = np.where(keep, np.hypot(xs - cx, ys - cy), np.inf)
    if prefer_top:
        near = dist <= reach
        if inside is not None and (inside & near).any():
            near &= inside
        keep = _top_band(pts, near)
        if not keep.any():  # empty only when nothing is within reach
            keep = np.ones(len(xs), bool)
        if far is not None:
            if (keep & far).any():
                keep &= far
            elif (near & far).any():
                keep = _top_band(pts, near & far)
        cx, cy = xs[keep].mean(), ys[keep].mean()
        weight = np.where(keep, np.hypot(xs - cx, ys - cy), np.inf)
    k = int(np.argmin(weight))
    return Sighting(det, int(xs[k]), int(ys[k]), float(dist[k]), pts[k])


def aim_region(region: np.ndarray, others: np.ndarray | None = None, edge: float = EDGE_MARGIN) -> np.ndarray:
    """The pixels of a receptacle's ``region`` (bool HxW) a put may aim at: not within ``edge``
    (a share of the width / height) of the frame's border, where the depth and the detector's
    mask are least sure, and not on ``others`` (bool HxW: other receptacles' detections, so
    that a put aimed at a side table does not land on the bed beside it, whose mask the table's
    box overlaps). The border rule is dropped when it would leave no pixel; the other
    receptacles' rule when it would leave less than ``AIM_MIN_SHARE`` of the region (masks of
    neighbours at one depth can cover the whole target: a sliver left over would be its edge)."""
    h, w = region.shape
    inner = np.zeros_like(region)
    mh, mw = int(math.ceil(edge * h)), int(math.ceil(edge * w))
    inner[mh : h - mh, mw : w - mw] = True
    keep = region & inner if (region & inner).any() else region
    if others is not None:
        free = keep & ~others
        if free.any() and free.sum() >= AIM_MIN_SHARE * keep.sum():
            keep = free
    return keep


def other_receptacles(body: Body, det: Detection, labels: frozenset[str]) -> np.ndarray | None:
    """bool HxW: the pixels of the frame's detections of ``labels`` other than ``det`` (None
    when there is none)."""
    obs = body.obs
    assert obs is not None
    shape = obs.depth.shape
    out = None
    for d in body.detections:
        if d is det or d.label not in labels:
            continue
        r = d.region(shape)
        out = r.copy() if out is None else out | r
    return out


def _top_band(pts: np.ndarray, among: np.ndarray, band_m: float = 0.08) -> np.ndarray:
    """bool per point: among ``among``, those within ``band_m`` of the 90th height percentile."""
    if not among.any():
        return among
    return among & (pts[:, 2] >= np.percentile(pts[among, 2], 90) - band_m)


def receptacle_in_view(body: Body, labels: frozenset[str]) -> Detection | None:
    """The largest detection of any of ``labels`` in the current frame."""
    obs = body.obs
    assert obs is not None
    shape = obs.depth.shape
    best = None
    for det in body.detections:
        if det.label in labels:
            area = int(det.region(shape).sum())
            if best is None or area > best[0]:
                best = (area, det)
    return best[1] if best else None
