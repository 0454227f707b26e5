"""Typed messages between a tidee server, its agents and its viewers.

Every message is a dataclass of plain fields (str, int, float, bool, None, lists and
dicts of those) plus numpy arrays; ``protocol/codec.py`` turns them into bytes and back.
Nothing here imports pybullet or torch.

Frames and units (the whole system uses these):
  * the *start frame* is the agent's pose at reset: x forward, y left, z up, metres,
    origin on the floor under the agent;
  * ``Observation.camera_pose`` is the 4x4 transform from the camera's optical frame
    (x right, y down, z forward, as OpenCV) to the start frame, so a pixel (u, v) with
    depth d maps to ``camera_pose @ [d (u-cx)/fx, d (v-cy)/fy, d, 1]``;
  * ``Observation.agent_pose`` is (x, y, yaw_deg, pitch_deg) in the start frame; yaw is
    counter-clockwise from +x, pitch positive looking *down* (AI2THOR's horizon).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from tidee import argtypes
from tidee.options import option
from tidee.protocol.vocab import ROOM_TYPES, RoomType

PROTOCOL_VERSION = 1


class ActionName(str, Enum):
    MoveAhead = "MoveAhead"
    MoveBack = "MoveBack"
    MoveLeft = "MoveLeft"
    MoveRight = "MoveRight"
    RotateLeft = "RotateLeft"
    RotateRight = "RotateRight"
    LookUp = "LookUp"
    LookDown = "LookDown"
    PickupObject = "PickupObject"
    PutObject = "PutObject"
    OpenObject = "OpenObject"
    CloseObject = "CloseObject"
    Done = "Done"


# Actions that act on whatever is at a pixel: they need x and y in [0, 1].
INTERACT_M = 1.5  # the server acts on things (and puts at a reach) up to this far from the eye, m

PIXEL_ACTIONS = frozenset(
    {ActionName.PickupObject, ActionName.PutObject, ActionName.OpenObject, ActionName.CloseObject}
)


class ActionError(str, Enum):
    """Why an action failed. Every failed action carries exactly one of these."""

    blocked = "blocked"  # a move would collide with furniture or a wall
    look_limit = "look_limit"  # pitch would leave [-30, 60] degrees
    too_far = "too_far"  # the thing at the pixel (or the reach) is beyond INTERACT_M
    nothing_there = "nothing_there"  # the ray hit nothing (or only wall/ceiling)
    not_pickupable = "not_pickupable"
    not_receptacle = "not_receptacle"
    not_openable = "not_openable"
    no_free_space = "no_free_space"  # no stable pose for the held object there
    receptacle_closed = "receptacle_closed"
    already_open = "already_open"
    already_closed = "already_closed"
    hands_full = "hands_full"
    hands_empty = "hands_empty"
    episode_over = "episode_over"  # Done was called or the step cap reached
    walkthrough = "walkthrough"  # an interaction during a rearrangement's walkthrough phase


class ErrorCode(str, Enum):
    """Why a *request* was rejected (as opposed to an action that failed in the world)."""

    malformed = "malformed"  # bytes that do not decode
    bad_version = "bad_version"
    invalid_field = "invalid_field"  # a field of the wrong type or out of range
    oversized = "oversized"
    unknown_session = "unknown_session"
    server_busy = "server_busy"  # too many sessions
    internal = "internal"


IMAGE_ENCODINGS = ("raw", "jpeg", "png")  # how observation images travel (protocol/README.md)


def _put_option(
    name: ActionName, field: str, value: Any, unit: str, bounds: str, within: Callable[[float], bool]
) -> float | None:
    """A PutObject-only number, checked: None stays None; NaN is outside any bounds."""
    if value is None:
        return None
    if name != ActionName.PutObject:
        raise ValueError(f"{name.value} takes no {field} (only PutObject does); got {field}={value!r}")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"PutObject's {field} must be a number of {unit}, got {value!r}")
    if not within(float(value)):
        raise ValueError(f"PutObject's {field} must be in {bounds} {unit}, got {value!r}")
    return float(value)


@dataclass
class Action:
    name: ActionName
    x: float | None = None  # normalised pixel column in [0, 1] (left to right)
    y: float | None = None  # normalised pixel row in [0, 1] (top to bottom)
    # PutObject only: degrees (counter-clockwise, [-180, 180]) to turn the held object from how it
    # lay when picked up (it turns with the agent while held) before putting it down; None: put it
    # down with its x axis along the agent's heading.
    yaw: float | None = None
    # PutObject only: metres along the pixel's ray, (0, 10]: put it on the surface under that point
    # (reaching over a receptacle's edge: a counter top at eye height is seen edge-on); None: where
    # the ray first meets something.
    reach: float | None = None

    def __post_init__(self) -> None:
        self.name = ActionName(self.name)
        self.yaw = _put_option(
            self.name, "yaw", self.yaw, "degrees", "[-180, 180]", lambda v: -180 <= v <= 180
        )
        self.reach = _put_option(self.name, "reach", self.reach, "metres", "(0, 10]", lambda v: 0 < v <= 10)
        if self.name in PIXEL_ACTIONS:
            for axis, v in (("x", self.x), ("y", self.y)):
                if v is None or not (0.0 <= float(v) <= 1.0):
                    raise ValueError(f"{self.name.value} needs {axis} in [0, 1], got {v!r}")
            self.x, self.y = float(self.x), float(self.y)  # type: ignore[arg-type]
        elif self.x is not None or self.y is not None:
            raise ValueError(f"{self.name.value} takes no pixel; got x={self.x!r}, y={self.y!r}")


@dataclass
class EpisodeSpec:
    """What a reset asks for: which room, which mess, which camera."""

    room_type: RoomType = option("LivingRoom", "the room type")
    seed: int = option(0, "room seed (200-204 are test rooms)", type=argtypes.non_negative_int)
    mess_index: int | None = option(
        None,
        "messy configuration index (none: the tidy room; an agent plays mess 0 unless it is given "
        "this or --rearrange-index)",
        type=argtypes.non_negative_int,
    )
    resolution: int = option(256, "square images, pixels a side", type=argtypes.resolution)
    camera_height: float = option(0.9015, "camera height, metres (the paper's)", cli=False)
    max_steps: int = option(1000, "the episode's step budget", type=argtypes.max_steps)
    pose_noise: bool = option(False, "LoCoBot-like pose noise: 0.005 m per move, 0.5 deg per turn")
    depth_noise: bool = option(False, "noisy depth")
    start_seed: int | None = option(None, "spawn pose; None: near the room centre, from seed", cli=False)
    rearrange_index: int | None = option(
        None,
        "a 2-phase rearrangement episode: configuration index of the room (walkthrough the goal state, "
        "then unshuffle the shuffled one; see protocol/README.md)",
        type=argtypes.non_negative_int,
    )
    walkthrough_steps: int = option(
        250,
        "a rearrangement's walkthrough step budget (max_steps is the unshuffle's)",
        type=argtypes.max_steps,
    )

    def __post_init__(self) -> None:
        if self.room_type not in ROOM_TYPES:
            raise ValueError(f"room_type must be one of {ROOM_TYPES}, got {self.room_type!r}")
        if not (16 <= int(self.resolution) <= 1024):
            raise ValueError(f"resolution must be in [16, 1024], got {self.resolution}")
        if not (0.2 <= float(self.camera_height) <= 2.0):
            raise ValueError(f"camera_height must be in [0.2, 2.0] m, got {self.camera_height}")
        if not (1 <= int(self.max_steps) <= 100_000):
            raise ValueError(f"max_steps must be in [1, 100000], got {self.max_steps}")
        if int(self.seed) < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.mess_index is not None and int(self.mess_index) < 0:
            raise ValueError(f"mess_index must be >= 0 or None, got {self.mess_index}")
        if self.start_seed is not None and int(self.start_seed) < 0:
            raise ValueError(f"start_seed must be >= 0 or None, got {self.start_seed}")
        if self.rearrange_index is not None:
            if int(self.rearrange_index) < 0:
                raise ValueError(f"rearrange_index must be >= 0 or None, got {self.rearrange_index}")
            if self.mess_index is not None:
                raise ValueError(
                    "give mess_index (a tidying episode) or rearrange_index (a rearrangement), not both"
                )
        if not (1 <= int(self.walkthrough_steps) <= 100_000):
            raise ValueError(f"walkthrough_steps must be in [1, 100000], got {self.walkthrough_steps}")


@dataclass
class GroundTruth:
    """Privileged state: only sent when a client asks for it (oracle modes, evaluation)."""

    instance_seg: np.ndarray  # int32 HxW: index into ``objects``, -1 for none
    objects: list[dict[str, Any]]  # scene-export entries (see server/scene.py)


@dataclass
class Observation:
    session: str
    step: int
    rgb: np.ndarray  # uint8 HxWx3
    depth: np.ndarray  # float32 HxW, metres along the optical axis
    camera_pose: np.ndarray  # float64 4x4, optical frame -> start frame
    agent_pose: tuple[float, float, float, float]  # x, y, yaw_deg, pitch_deg (start frame)
    intrinsics: np.ndarray  # float64 3x3
    held: str | None = None  # object type held, if any
    held_id: str | None = None
    last_action: str | None = None
    success: bool = True
    error: str | None = None  # an ActionError value when success is False
    message: str = ""  # human-readable detail for the error
    done: bool = False
    steps_left: int = 0
    ground_truth: GroundTruth | None = None
    phase: str | None = None  # a rearrangement's phase (REARRANGE_PHASES); None in a tidying episode


def _check_encoding(encoding: str) -> None:
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"encoding must be one of {IMAGE_ENCODINGS}, got {encoding!r}")


@dataclass
class ResetRequest:
    session: str
    spec: EpisodeSpec = field(default_factory=EpisodeSpec)
    ground_truth: bool = False
    encoding: str = "raw"  # raw | jpeg | png  (images on the wire)
    protocol_version: int = PROTOCOL_VERSION

    def __post_init__(self) -> None:
        _check_encoding(self.encoding)


@dataclass
class StepRequest:
    session: str
    action: Action
    ground_truth: bool = False
    encoding: str = "raw"
    protocol_version: int = PROTOCOL_VERSION

    def __post_init__(self) -> None:
        _check_encoding(self.encoding)


REARRANGE_PHASES = ("walkthrough", "unshuffle")


@dataclass
class PhaseRequest:
    """Rearrangement: end the walkthrough and start the unshuffle phase (the reply is its first
    Observation: the shuffled room, the agent back at its start pose)."""

    session: str
    phase: str = "unshuffle"
    ground_truth: bool = False
    encoding: str = "raw"
    protocol_version: int = PROTOCOL_VERSION

    def __post_init__(self) -> None:
        _check_encoding(self.encoding)
        if self.phase != "unshuffle":
            raise ValueError(
                f"phase must be 'unshuffle' (the walkthrough starts at reset), got {self.phase!r}"
            )


@dataclass
class StateRequest:
    """Evaluation only: the full scene state (the scene export plus mess records)."""

    session: str
    protocol_version: int = PROTOCOL_VERSION


@dataclass
class StateReply:
    session: str
    scene: dict[str, Any]


@dataclass
class CloseRequest:
    session: str
    protocol_version: int = PROTOCOL_VERSION


@dataclass
class CloseReply:
    session: str
    closed: bool  # False: there was no such session (already freed)


@dataclass
class ServerInfoRequest:
    """Asked of every live server at once (``tidee/sim/*/info``) by a client choosing one: how full
    is it, and does it hold ``session`` already?"""

    session: str | None = None
    protocol_version: int = PROTOCOL_VERSION


@dataclass
class ServerInfo:
    server_id: str
    sessions: int  # held now, being opened, or announced (another client's token is up, no reset yet)
    max_sessions: int  # the most it holds at once (max_sessions)
    holds_session: bool = False  # the request's session is one of them


@dataclass
class ErrorReply:
    code: ErrorCode
    message: str
    session: str | None = None


# --- agent -> viewer telemetry (key: tidee/agent/{session}/telemetry/{kind}) -----------
#
# All positions are in the episode's start frame (x forward, y left, z up, metres).
# A top-down grid ``g`` with ``origin`` (x0, y0) and ``cell`` c covers cell (i, j) =
# [x0 + i c, x0 + (i+1) c) x [y0 + j c, y0 + (j+1) c): axis 0 runs along +x, axis 1
# along +y. Every message carries the agent ``step`` it describes; viewers keep the
# latest of each kind (a ring buffer of one), so a slow viewer drops frames, never lags.

TELEMETRY_KINDS = ("status", "frame", "maps", "memory", "walkthrough", "search", "ack", "summary")
PHASES = (
    "idle",
    "walkthrough",
    "mapping",
    "searching",
    "approaching",
    "picking",
    "inferring",
    "placing",
    "searching_receptacle",
    "dropping",
    "opening",
    "done",
)
COMMAND_KINDS = ("pause", "resume", "step", "new_episode", "preference")


@dataclass
class ReceptaclePrediction:
    label: str
    prob: float


@dataclass
class AgentStatus:
    """Kind ``status``: what the agent is doing (a few hundred bytes; every step)."""

    session: str
    step: int
    phase: str  # one of PHASES
    episode: dict[str, Any]  # room_type, seed, mess_index, variant, perception, ...
    pose: tuple[float, float, float, float]  # x, y, yaw_deg, pitch_deg (believed)
    paused: bool = False
    target_object: str | None = None  # the OOP object being handled (label)
    target_id: int | None = None  # its object-memory id
    target_receptacle: str | None = None
    predictions: list[ReceptaclePrediction] = field(default_factory=list)  # top-5 receptacles
    held: str | None = None
    objects_fixed: int = 0  # puts of OOP objects that succeeded
    oop_found: int = 0
    done: bool = False
    message: str = ""  # the last event, for people
    trajectory: np.ndarray | None = None  # float32 Nx2: believed positions so far (subsampled)
    path: np.ndarray | None = None  # float32 Mx2: planned path to the current goal
    goal: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.phase not in PHASES:
            raise ValueError(f"phase must be one of {PHASES}, got {self.phase!r}")


@dataclass
class Detection2D:
    label: str
    score: float
    box: tuple[float, float, float, float]  # x0, y0, x1, y1 in pixels
    oop_prob: float | None = None
    track_id: int | None = None  # object-memory id it merged into


@dataclass
class AgentFrame:
    """Kind ``frame``: the current RGB-D frame and the detections in it."""

    session: str
    step: int
    rgb: np.ndarray  # uint8 HxWx3
    depth: np.ndarray  # float32 HxW, metres
    camera_pose: np.ndarray  # float64 4x4, optical -> start frame
    intrinsics: np.ndarray  # float64 3x3
    detections: list[Detection2D] = field(default_factory=list)
    perception: str = "oracle"  # which perception produced the detections


@dataclass
class MapSnapshot:
    """Kind ``maps``: the 2D occupancy map and the semantic voxel map as points."""

    session: str
    step: int
    origin: tuple[float, float]  # start-frame (x, y) of grid cell (0, 0)'s corner
    cell: float  # metres per 2D cell
    occupancy: np.ndarray  # uint8 XxY: 0 unknown, 1 free, 2 obstacle
    explored: np.ndarray  # bool XxY
    voxel_size: float  # metres per voxel edge (x, y); points are centres
    points: np.ndarray  # float32 Nx3: occupied voxel centres
    point_labels: np.ndarray  # int16 N: index into ``classes``, -1 unlabelled
    classes: list[str] = field(default_factory=list)


@dataclass
class TrackedObjectMsg:
    id: int
    label: str
    score: float
    centroid: tuple[float, float, float]
    box_min: tuple[float, float, float]
    box_max: tuple[float, float, float]
    oop_prob: float | None = None
    out_of_place: bool = False  # a rearrangement's unshuffle: believed moved or toggled
    held: bool = False
    # A rearrangement's unshuffle, an object believed moved: where it goes back (the centre of
    # the walkthrough box it was matched to)
    goal_centroid: tuple[float, float, float] | None = None


@dataclass
class ObjectMemoryMsg:
    """Kind ``memory``: every object the agent tracks."""

    session: str
    step: int
    objects: list[TrackedObjectMsg] = field(default_factory=list)


@dataclass
class WalkthroughMemoryMsg:
    """Kind ``walkthrough``: what a rearrangement's walkthrough remembers of the goal room, sent
    when the walkthrough ends. ``step`` is the walkthrough's last step; each object's ``id`` is
    its index in that memory, its ``score`` 1.0 (the memory keeps no detection score)."""

    session: str
    step: int
    objects: list[TrackedObjectMsg] = field(default_factory=list)


@dataclass
class SearchHeatmap:
    """Kind ``search``: where the agent looks for ``target`` (a top-down grid)."""

    session: str
    step: int
    target: str
    origin: tuple[float, float]
    cell: float
    heatmap: np.ndarray  # float32 XxY in [0, 1]
    points: np.ndarray  # float32 Kx2: ranked search points (x, y)
    source: str = "search_network"


@dataclass
class EpisodeSummary:
    """Kind ``summary``: how an episode ended, sent once when it ends (also ``summary.json``).

    ``moved``, ``found``, ``plausible`` and ``false_picks`` are scored after the episode
    against the server's privileged state (evaluation, never the agent's decisions);
    they are None when the server gave no state.
    """

    session: str
    episode: dict[str, Any]  # room_type, seed, mess_index, variant, perception, ...
    steps: int
    wall_s: float
    end_reason: str
    put_away: int  # puts of out-of-place objects that succeeded
    moved: int | None = None  # objects the mess-up moved
    found: int | None = None  # of those, how many the agent found (picked or flagged)
    plausible: int | None = None  # moved objects whose final receptacle the judge accepts
    false_picks: int | None = None  # objects picked that the mess-up had not moved
    replay: str = ""  # the command that replays the episode's log
    rearrange: dict[str, Any] | None = None  # a rearrangement's RoomR metrics (success, fixed_strict, ...)


@dataclass
class AgentCommand:
    """A viewer -> agent command (key ``tidee/agent/{session}/cmd``)."""

    kind: str  # one of COMMAND_KINDS
    command_id: str = ""
    room_type: str | None = None  # new_episode
    seed: int | None = None
    mess_index: int | None = None
    text: str | None = None  # preference: "I want my alarm clock on the desk"

    def __post_init__(self) -> None:
        if self.kind not in COMMAND_KINDS:
            raise ValueError(f"kind must be one of {COMMAND_KINDS}, got {self.kind!r}")
        if self.kind == "preference" and not (self.text and self.text.strip()):
            raise ValueError("a preference command needs non-empty text")
        if self.room_type is not None and self.room_type not in ROOM_TYPES:
            raise ValueError(f"room_type must be one of {ROOM_TYPES}, got {self.room_type!r}")


@dataclass
class CommandAck:
    """Kind ``ack``: the agent's answer to an AgentCommand."""

    session: str
    command_id: str
    kind: str
    ok: bool
    message: str = ""
