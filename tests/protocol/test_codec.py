"""The codec: round trips of every message, image encodings, and every rejection path."""

from __future__ import annotations

import dataclasses
import json
import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from tidee.protocol.codec import ALIGN, DEFAULT_MAX_BYTES, MAGIC, MESSAGE_TYPES, ProtocolError, decode, encode
from tidee.protocol.messages import (
    PROTOCOL_VERSION,
    Action,
    ActionName,
    AgentCommand,
    AgentFrame,
    AgentStatus,
    CloseReply,
    CloseRequest,
    CommandAck,
    Detection2D,
    EpisodeSpec,
    EpisodeSummary,
    ErrorCode,
    ErrorReply,
    GroundTruth,
    MapSnapshot,
    ObjectMemoryMsg,
    Observation,
    PhaseRequest,
    ReceptaclePrediction,
    ResetRequest,
    SearchHeatmap,
    ServerInfo,
    ServerInfoRequest,
    StateReply,
    StateRequest,
    StepRequest,
    TrackedObjectMsg,
    WalkthroughMemoryMsg,
)

PREFIX = struct.Struct("<4sHI")


def observation(resolution: int = 32, ground_truth: bool = False, smooth: bool = False) -> Observation:
    rng = np.random.default_rng(0)
    r = resolution
    if smooth:  # something JPEG can compress faithfully
        ramp = np.linspace(0, 255, r, dtype=np.float32)
        rgb = np.stack(
            [np.add.outer(ramp, ramp) / 2, np.tile(ramp, (r, 1)), np.tile(ramp[:, None], (1, r))], axis=-1
        )
        rgb = rgb.astype(np.uint8)
    else:
        rgb = rng.integers(0, 256, (r, r, 3), dtype=np.uint8)
    gt = (
        GroundTruth(
            instance_seg=rng.integers(-1, 5, (r, r), dtype=np.int32),
            objects=[
                {"id": "Mug_0", "type": "Mug", "position": [1.0, 2.0, 0.8], "moved": True, "parent": None}
            ],
        )
        if ground_truth
        else None
    )
    return Observation(
        session="s1",
        step=3,
        rgb=rgb,
        depth=rng.uniform(0.05, 20.0, (r, r)).astype(np.float32),
        camera_pose=rng.normal(size=(4, 4)),
        agent_pose=(0.25, -0.5, 90.0, 30.0),
        intrinsics=np.array([[16.0, 0, 15.5], [0, 16.0, 15.5], [0, 0, 1]]),
        held="Mug",
        held_id="Mug_0",
        last_action="PickupObject",
        success=False,
        error="too_far",
        message="1.7 m away",
        done=False,
        steps_left=997,
        ground_truth=gt,
    )


EXAMPLES: list[Any] = [
    Action(ActionName.MoveAhead),
    Action(ActionName.PutObject, 0.0, 1.0),
    EpisodeSpec(room_type="Kitchen", seed=12, mess_index=3, resolution=128, pose_noise=True, start_seed=7),
    GroundTruth(instance_seg=np.full((4, 5), -1, np.int32), objects=[]),
    observation(),
    observation(ground_truth=True),
    ResetRequest("s1", EpisodeSpec(room_type="Bathroom", seed=4), ground_truth=True, encoding="png"),
    StepRequest("s1", Action(ActionName.OpenObject, 0.5, 0.25), encoding="jpeg"),
    StepRequest("s1", Action(ActionName.Done)),
    StepRequest("s1", Action(ActionName.PutObject, 0.5, 0.75, yaw=-42.5, reach=0.8)),
    StateRequest("s1"),
    PhaseRequest("s1", ground_truth=True, encoding="png"),
    StateReply("s1", {"objects": [{"id": "a", "size": [1, 2, 3]}], "agent": {"x": 1.5, "held": None}}),
    CloseRequest("s1"),
    CloseReply("s1", closed=True),
    ServerInfoRequest("s1"),
    ServerInfoRequest(),
    ServerInfo("sim0", sessions=3, max_sessions=16, holds_session=True),
    ErrorReply(ErrorCode.server_busy, "full", session=None),
    ReceptaclePrediction("Desk", 0.4),
    AgentStatus(
        session="s1",
        step=7,
        phase="placing",
        episode={"room_type": "Bedroom", "seed": 201},
        pose=(0.5, -0.25, 90.0, 30.0),
        target_object="AlarmClock",
        target_id=3,
        target_receptacle="Desk",
        predictions=[ReceptaclePrediction("Desk", 0.6), ReceptaclePrediction("SideTable", 0.3)],
        held="AlarmClock",
        objects_fixed=1,
        oop_found=2,
        trajectory=np.zeros((3, 2), np.float32),
        path=np.ones((4, 2), np.float32),
        goal=(1.0, 2.0),
    ),
    Detection2D("Mug", 0.9, (1.0, 2.0, 10.0, 12.0), oop_prob=0.8, track_id=4),
    AgentFrame(
        "s1",
        7,
        np.zeros((8, 8, 3), np.uint8),
        np.ones((8, 8), np.float32),
        np.eye(4),
        np.eye(3),
        [Detection2D("Mug", 0.9, (1.0, 2.0, 5.0, 6.0))],
    ),
    MapSnapshot(
        "s1",
        7,
        (-6.4, -6.4),
        0.05,
        np.zeros((6, 5), np.uint8),
        np.zeros((6, 5), bool),
        0.1,
        np.zeros((3, 3), np.float32),
        np.array([-1, 0, 5], np.int16),
        ["Mug", "Desk"],
    ),
    TrackedObjectMsg(2, "Mug", 1.0, (1.0, 0.0, 0.9), (0.9, -0.1, 0.85), (1.1, 0.1, 0.95), 0.7, True),
    ObjectMemoryMsg(
        "s1", 7, [TrackedObjectMsg(2, "Mug", 1.0, (1.0, 0.0, 0.9), (0.9, -0.1, 0.85), (1.1, 0.1, 0.95))]
    ),
    ObjectMemoryMsg(  # a rearrangement's unshuffle: a mug believed moved, and where it goes back
        "s1",
        7,
        [
            TrackedObjectMsg(
                2,
                "Mug",
                1.0,
                (1.0, 0.0, 0.9),
                (0.9, -0.1, 0.85),
                (1.1, 0.1, 0.95),
                None,
                True,
                goal_centroid=(-0.5, 1.25, 0.8),
            )
        ],
    ),
    WalkthroughMemoryMsg(
        "s1",
        54,
        [
            TrackedObjectMsg(0, "Mug", 1.0, (-0.5, 1.25, 0.8), (-0.55, 1.2, 0.75), (-0.45, 1.3, 0.85)),
            TrackedObjectMsg(1, "Fridge", 1.0, (2.0, 0.0, 0.9), (1.6, -0.4, 0.0), (2.4, 0.4, 1.8)),
        ],
    ),
    SearchHeatmap(
        "s1", 7, "Desk", (-6.4, -6.4), 0.1, np.zeros((4, 4), np.float32), np.zeros((2, 2), np.float32)
    ),
    AgentCommand(kind="preference", command_id="c1", text="I want my alarm clock on the desk"),
    CommandAck("s1", "c1", "preference", True, "noted"),
    EpisodeSummary(
        "s1",
        {"room_type": "Kitchen", "seed": 200, "mess_index": 0},
        120,
        33.5,
        "done",
        4,
        moved=5,
        found=5,
        plausible=4,
        false_picks=0,
        replay="tidee viewer --replay runs/Kitchen_200_mess0",
    ),
    EpisodeSummary(
        "s1",
        {"room_type": "Kitchen", "seed": 201, "rearrange_index": 1},
        92,
        4.1,
        "restored what it found",
        3,
        rearrange={
            "success": False,
            "fixed_strict": 0.75,
            "misplaced": 0.25,
            "energy": 0.25,
            "start_misplaced": 4,
            "fixed": 3,
            "newly_misplaced": 0,
        },
    ),
]


def assert_same(a: Any, b: Any, path: str = "") -> None:
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, path
        assert np.array_equal(a, b), path
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), path
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    else:
        assert a == b and type(a) is type(b), f"{path}: {a!r} != {b!r}"


def test_examples_cover_every_message_type() -> None:
    assert {type(m).__name__ for m in EXAMPLES} == set(MESSAGE_TYPES)


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_raw_round_trip(msg: Any) -> None:
    assert_same(msg, decode(encode(msg)))


def test_raw_arrays_are_zero_copy_and_aligned() -> None:
    frame = encode(observation())
    header_len = PREFIX.unpack_from(frame)[2]
    body_start = PREFIX.size + header_len
    assert body_start % ALIGN == 0
    fields = json.loads(frame[PREFIX.size : body_start])["fields"]
    for name in ("rgb", "depth", "camera_pose", "intrinsics"):
        assert fields[name]["offset"] % ALIGN == 0 and fields[name]["encoding"] == "raw"
    obs = decode(frame)
    assert not obs.rgb.flags.writeable  # a view of the frame, not a copy
    assert obs.rgb.base is not None


def test_png_is_lossless_for_rgb_and_millimetric_for_depth() -> None:
    obs = observation(64, ground_truth=True)
    out = decode(encode(obs, "png"))
    assert np.array_equal(out.rgb, obs.rgb)
    assert out.depth.dtype == np.float32 and np.abs(out.depth - obs.depth).max() <= 0.0005 + 1e-6
    assert_same(obs.ground_truth, out.ground_truth)  # not an image: stays raw
    assert_same(obs.camera_pose, out.camera_pose)


def test_jpeg_is_close_and_smaller() -> None:
    obs = observation(64, smooth=True)
    frame = encode(obs, "jpeg")
    assert len(frame) < len(encode(obs))
    out = decode(frame)
    assert out.rgb.shape == obs.rgb.shape and out.rgb.dtype == np.uint8
    assert np.abs(out.rgb.astype(int) - obs.rgb).mean() < 3.0
    assert np.abs(out.depth - obs.depth).max() <= 0.0005 + 1e-6


def test_depth_png_clips_what_16_bits_cannot_hold() -> None:
    obs = observation(16)
    obs.depth[0, 0], obs.depth[0, 1], obs.depth[0, 2] = np.nan, 100.0, -1.0
    out = decode(encode(obs, "png"))
    assert out.depth[0, 0] == 0.0 and out.depth[0, 1] == pytest.approx(65.535) and out.depth[0, 2] == 0.0


def test_only_a_put_takes_a_yaw_and_a_reach() -> None:
    assert Action(ActionName.PutObject, 0.5, 0.5, yaw=90).yaw == 90.0
    assert Action(ActionName.PutObject, 0.5, 0.5, reach=1).reach == 1.0
    assert Action(ActionName.PutObject, 0.5, 0.5).yaw is None
    for bad, says in [
        (dict(name=ActionName.PickupObject, x=0.5, y=0.5, yaw=10.0), "PickupObject takes no yaw"),
        (dict(name=ActionName.RotateLeft, yaw=10.0), "RotateLeft takes no yaw"),
        (dict(name=ActionName.PutObject, x=0.5, y=0.5, yaw=190.0), r"in \[-180, 180\] degrees, got 190"),
        (dict(name=ActionName.PutObject, x=0.5, y=0.5, yaw=float("nan")), "got nan"),
        (dict(name=ActionName.PutObject, x=0.5, y=0.5, yaw=True), "a number of degrees, got True"),
        (dict(name=ActionName.OpenObject, x=0.5, y=0.5, reach=1.0), "OpenObject takes no reach"),
        (
            dict(name=ActionName.PutObject, x=0.5, y=0.5, reach=0.0),
            r"reach must be in \(0, 10\] metres, got 0",
        ),
        (dict(name=ActionName.PutObject, x=0.5, y=0.5, reach="far"), "a number of metres, got 'far'"),
    ]:
        with pytest.raises(ValueError, match=says):
            Action(**bad)


def test_encode_refuses_arrays_that_break_the_contract() -> None:
    obs = observation()
    with pytest.raises(TypeError, match="field 'depth' must be float32 NxN, got float64"):
        encode(dataclasses.replace(obs, depth=obs.depth.astype(np.float64)))
    with pytest.raises(TypeError, match="field 'rgb' must be uint8 NxNx3"):
        encode(dataclasses.replace(obs, rgb=obs.rgb[..., 0]))
    with pytest.raises(ValueError, match="encoding must be one of"):
        encode(obs, "gif")
    with pytest.raises(TypeError, match="not a message type"):
        encode({"type": "StepRequest"})


def test_numpy_scalars_and_tuples_in_plain_fields_become_json() -> None:
    reply = StateReply("s1", {"x": np.float32(1.5), "p": (1, 2), "a": np.arange(3)})
    assert decode(encode(reply)).scene == {"x": 1.5, "p": [1, 2], "a": [0, 1, 2]}


# --- rejection paths --------------------------------------------------------------------


def reframe(
    frame: bytes,
    mutate: Callable[[dict], Any] | None = None,
    *,
    body: bytes | None = None,
    magic: bytes = MAGIC,
    version: int = PROTOCOL_VERSION,
) -> bytes:
    """``frame`` with its header passed through ``mutate`` (which edits it in place)."""
    header_len = PREFIX.unpack_from(frame)[2]
    header = json.loads(frame[PREFIX.size : PREFIX.size + header_len])
    if mutate is not None:
        mutate(header)
    raw = json.dumps(header).encode()
    body = frame[PREFIX.size + header_len :] if body is None else body
    return PREFIX.pack(magic, version, len(raw)) + raw + body


def rejects(frame: bytes, code: ErrorCode, *fragments: str, **kwargs: Any) -> None:
    with pytest.raises(ProtocolError) as info:
        decode(frame, **kwargs)
    assert info.value.code == code, info.value.message
    for fragment in fragments:
        assert fragment in info.value.message, info.value.message


STEP = encode(StepRequest("s1", Action(ActionName.PickupObject, 0.5, 0.5)))
RESET = encode(ResetRequest("s1", EpisodeSpec()))
OBS = encode(observation())


def set_in(path: str, value: Any) -> Callable[[dict], None]:
    def mutate(header: dict) -> None:
        *parents, leaf = path.split(".")
        node = header["fields"]
        for p in parents:
            node = node[p]
        node[leaf] = value

    return mutate


def delete(path: str) -> Callable[[dict], None]:
    def mutate(header: dict) -> None:
        *parents, leaf = path.split(".")
        node = header["fields"]
        for p in parents:
            node = node[p]
        del node[leaf]

    return mutate


def test_bad_magic() -> None:
    rejects(reframe(STEP, magic=b"HTTP"), ErrorCode.malformed, "bad magic")


def test_garbage_and_empty() -> None:
    rejects(b"", ErrorCode.malformed, "shorter than the 10-byte prefix")
    rejects(b"GET / HTTP/1.1\r\n\r\n", ErrorCode.malformed, "bad magic")


def test_wrong_protocol_version() -> None:
    rejects(
        reframe(STEP, version=PROTOCOL_VERSION + 1), ErrorCode.bad_version, f"version {PROTOCOL_VERSION + 1}"
    )
    rejects(reframe(STEP, set_in("protocol_version", 99)), ErrorCode.bad_version, "'protocol_version'", "99")


def test_truncated_header_and_buffers() -> None:
    rejects(STEP[:20], ErrorCode.malformed, "truncated")
    rejects(OBS[:-8], ErrorCode.malformed, "truncated", "field 'intrinsics'")


def test_header_not_json() -> None:
    rejects(PREFIX.pack(MAGIC, PROTOCOL_VERSION, 5) + b"{nope", ErrorCode.malformed, "not valid UTF-8 JSON")
    raw = b'{"type":"StepRequest","fields":{"session":NaN}}'
    rejects(PREFIX.pack(MAGIC, PROTOCOL_VERSION, len(raw)) + raw, ErrorCode.malformed, "NaN")
    raw = b"[1, 2]"
    rejects(PREFIX.pack(MAGIC, PROTOCOL_VERSION, len(raw)) + raw, ErrorCode.malformed, "'type' and 'fields'")


def test_unknown_and_unexpected_message_types() -> None:
    rejects(
        reframe(STEP, lambda h: h.update(type="Teleport")),
        ErrorCode.malformed,
        "unknown message type 'Teleport'",
    )
    rejects(RESET, ErrorCode.malformed, "expected StepRequest, got ResetRequest", expected=StepRequest)


@pytest.mark.parametrize(
    "mutate, fragments",
    [
        (set_in("action.x", "abc"), ["field 'action.x' must be a number", "'abc'"]),
        (set_in("action.name", "Fly"), ["field 'action.name' must be one of", "'Fly'"]),
        (set_in("action.x", 1.5), ["invalid field 'action'", "x in [0, 1]", "1.5"]),
        (set_in("action.x", None), ["invalid field 'action'", "needs x"]),
        (set_in("session", 5), ["field 'session' must be a string", "5"]),
        (set_in("ground_truth", 1), ["field 'ground_truth' must be a boolean"]),
        (set_in("encoding", "gif"), ["invalid StepRequest", "encoding must be one of", "'gif'"]),
        (set_in("action", "MoveAhead"), ["field 'action' must be an object"]),
        (set_in("extra", 1), ["unknown field 'extra'"]),
        (set_in("action.z", 1), ["unknown field 'action.z'"]),
        (set_in("action.yaw", 30.0), ["invalid field 'action'", "PickupObject takes no yaw"]),
        (set_in("action.yaw", "left"), ["field 'action.yaw' must be a number", "'left'"]),
        (set_in("action.reach", -1.0), ["invalid field 'action'", "PickupObject takes no reach"]),
        (delete("action"), ["field 'action' is required"]),
        (delete("action.name"), ["field 'action.name' is required"]),
    ],
)
def test_invalid_step_fields(mutate: Callable[[dict], None], fragments: list[str]) -> None:
    rejects(reframe(STEP, mutate), ErrorCode.invalid_field, *fragments)


@pytest.mark.parametrize(
    "mutate, fragments",
    [
        (set_in("spec.resolution", 5), ["invalid field 'spec'", "resolution must be in [16, 1024]"]),
        (
            set_in("spec.room_type", "Garage"),
            ["field 'spec.room_type' must be one of", "'Kitchen'", "'Garage'"],
        ),
        (set_in("spec.seed", True), ["field 'spec.seed' must be a 64-bit integer", "True"]),
        (set_in("spec.seed", 2.5), ["field 'spec.seed' must be a 64-bit integer"]),
        (set_in("spec.seed", 2**70), ["field 'spec.seed' must be a 64-bit integer"]),
        (set_in("spec.seed", -1), ["invalid field 'spec'", "seed must be >= 0"]),
        (set_in("spec.camera_height", "high"), ["field 'spec.camera_height' must be a number"]),
        (set_in("spec.mess_index", [1]), ["field 'spec.mess_index' must be a 64-bit integer"]),
    ],
)
def test_invalid_reset_fields(mutate: Callable[[dict], None], fragments: list[str]) -> None:
    rejects(reframe(RESET, mutate), ErrorCode.invalid_field, *fragments)


@pytest.mark.parametrize(
    "mutate, code, fragments",
    [
        (set_in("rgb.shape", [2, 2, 3]), ErrorCode.invalid_field, ["field 'rgb' declares", "nbytes is"]),
        (set_in("rgb.dtype", "<f4"), ErrorCode.invalid_field, ["field 'rgb' must be uint8 NxNx3", "float32"]),
        (set_in("rgb.dtype", "|O"), ErrorCode.invalid_field, ["field 'rgb.dtype' must be one of"]),
        (set_in("rgb.shape", [32, 32]), ErrorCode.invalid_field, ["field 'rgb' must be uint8 NxNx3"]),
        (set_in("rgb.shape", [32, -32, 3]), ErrorCode.invalid_field, ["field 'rgb.shape'"]),
        (set_in("rgb.offset", "0"), ErrorCode.invalid_field, ["field 'rgb.offset' must be a non-negative"]),
        (set_in("rgb.encoding", "gif"), ErrorCode.invalid_field, ["field 'rgb.encoding' must be one of"]),
        (set_in("camera_pose.encoding", "png"), ErrorCode.invalid_field, ["field 'camera_pose.encoding'"]),
        (set_in("camera_pose.shape", [3, 3]), ErrorCode.invalid_field, ["'camera_pose' must be float64 4x4"]),
        (set_in("depth", [[1.0]]), ErrorCode.invalid_field, ["field 'depth' must be an array descriptor"]),
        (set_in("rgb.offset", 10**9), ErrorCode.malformed, ["truncated", "field 'rgb'"]),
        (set_in("rgb.shape", [100000, 100000, 3]), ErrorCode.oversized, ["field 'rgb' declares", "limit"]),
        (
            set_in("agent_pose", [1, 2, 3]),
            ErrorCode.invalid_field,
            ["field 'agent_pose' must be a list of 4"],
        ),
        (set_in("agent_pose", [1, 2, 3, "x"]), ErrorCode.invalid_field, ["'agent_pose[3]' must be a number"]),
    ],
)
def test_invalid_observation_arrays(
    mutate: Callable[[dict], None], code: ErrorCode, fragments: list[str]
) -> None:
    rejects(reframe(OBS, mutate), code, *fragments)


def test_compressed_image_must_match_its_declared_shape() -> None:
    frame = encode(observation(32), "png")
    rejects(
        reframe(frame, set_in("rgb.shape", [16, 16, 3])),
        ErrorCode.invalid_field,
        "field 'rgb'",
        "compressed image is 32x32",
    )
    rejects(reframe(frame, set_in("depth.shape", [32, 16])), ErrorCode.invalid_field, "field 'depth'")
    jpeg = encode(observation(32), "jpeg")
    rejects(
        reframe(jpeg, set_in("rgb.shape", [48, 32, 3])), ErrorCode.invalid_field, "compressed image is 32x32"
    )


def test_corrupt_compressed_image() -> None:
    frame = encode(observation(32), "png")
    header_len = PREFIX.unpack_from(frame)[2]
    body = bytearray(frame[PREFIX.size + header_len :])
    body[:64] = b"\0" * 64  # rgb's PNG signature and header, gone
    rejects(reframe(frame, body=bytes(body)), ErrorCode.invalid_field, "field 'rgb'")


def test_oversized_frame() -> None:
    rejects(OBS, ErrorCode.oversized, f"frame is {len(OBS)} bytes", "limit is 1000", max_bytes=1000)
    assert DEFAULT_MAX_BYTES == 64 * 1024 * 1024


def test_protocol_error_names_its_code() -> None:
    err = ProtocolError(ErrorCode.malformed, "x")
    assert str(err) == "malformed: x" and err.code is ErrorCode.malformed and err.message == "x"


# --- raw-depth-mm: depth as uint16 millimetres under raw --------------------------------


def mm_frame(obs: Observation | None = None) -> bytes:
    return encode(observation(32) if obs is None else obs, raw_depth="mm")


def test_raw_depth_mm_round_trip_is_millimetric_and_half_the_bytes() -> None:
    obs = observation(64, ground_truth=True)
    frame = mm_frame(obs)
    header_len = PREFIX.unpack_from(frame)[2]
    fields = json.loads(frame[PREFIX.size : PREFIX.size + header_len])["fields"]
    assert fields["depth"]["encoding"] == "raw-depth-mm" and fields["depth"]["dtype"] == "<f4"
    assert fields["depth"]["nbytes"] == 64 * 64 * 2 and fields["depth"]["offset"] % ALIGN == 0
    assert fields["rgb"]["encoding"] == "raw"  # only depth maps change
    assert len(encode(obs)) - len(frame) >= 64 * 64 * 2 - 2 * ALIGN  # a longer header, padding
    out = decode(frame)
    assert out.depth.dtype == np.float32 and out.depth.shape == (64, 64)
    assert np.abs(out.depth - obs.depth).max() <= 0.0005 + 1e-6
    assert_same(obs.rgb, out.rgb)  # the rest is exact, and rgb still a view of the frame
    assert not out.rgb.flags.writeable
    assert_same(obs.ground_truth, out.ground_truth)
    assert_same(obs.camera_pose, out.camera_pose)
    frame_agent = AgentFrame("s1", 1, obs.rgb, obs.depth, np.eye(4), np.eye(3), [])
    assert np.abs(decode(encode(frame_agent, raw_depth="mm")).depth - obs.depth).max() <= 0.0005 + 1e-6


def test_raw_depth_mm_special_values() -> None:
    """0 and no-return (nan, +-inf, negative, under 0.5 mm) decode to 0; past 65.535 m clamps."""
    obs = observation(16)
    values = [0.0, 0.0004, 0.0005, 0.001, 1.234, 65.535, 65.5354, 100.0, np.nan, np.inf, -np.inf, -1.0, 3e38]
    obs.depth[0, : len(values)] = values
    out = decode(mm_frame(obs)).depth[0, : len(values)]
    want = [0.0, 0.0, 0.0, 0.001, 1.234, 65.535, 65.535, 65.535, 0.0, 0.0, 0.0, 0.0, 65.535]
    assert out.tolist() == np.array(want, np.float32).tolist()  # whole millimetres come back exactly
    assert decode(mm_frame(dataclasses.replace(obs, depth=np.zeros((16, 16), np.float32)))).depth.max() == 0.0


def test_raw_depth_mm_is_opt_in_and_f32_still_decodes() -> None:
    obs = observation(32)
    assert_same(obs, decode(encode(obs)))  # the default: float32, exact
    assert_same(obs, decode(encode(obs, raw_depth="f32")))
    png = decode(encode(obs, "png", raw_depth="mm"))  # png/jpeg carry millimetres either way
    assert np.abs(png.depth - obs.depth).max() <= 0.0005 + 1e-6
    with pytest.raises(ValueError, match="raw_depth must be one of"):
        encode(obs, raw_depth="f16")


def test_wire_depth_comes_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from tidee.protocol.codec import WIRE_DEPTH_ENV, wire_depth

    monkeypatch.delenv(WIRE_DEPTH_ENV, raising=False)
    assert wire_depth() == "f32"  # exact unless the server is told otherwise
    monkeypatch.setenv(WIRE_DEPTH_ENV, "mm")
    assert wire_depth() == "mm"
    monkeypatch.setenv(WIRE_DEPTH_ENV, "float16")
    with pytest.raises(ValueError, match="TIDEE_WIRE_DEPTH must be one of"):
        wire_depth()


@pytest.mark.parametrize(
    "mutate, code, fragments",
    [
        (set_in("depth.nbytes", 2046), ErrorCode.invalid_field, ["field 'depth'", "nbytes is 2046"]),
        (set_in("depth.nbytes", 2064), ErrorCode.invalid_field, ["field 'depth'", "raw-depth-mm"]),
        (set_in("depth.shape", [16, 16]), ErrorCode.invalid_field, ["field 'depth'", "nbytes is 2048"]),
        (set_in("depth.offset", 10**6), ErrorCode.malformed, ["truncated", "field 'depth'"]),
        (set_in("depth.dtype", "<u2"), ErrorCode.invalid_field, ["field 'depth' must be float32 NxN"]),
        (set_in("rgb.encoding", "raw-depth-mm"), ErrorCode.invalid_field, ["field 'rgb.encoding' must be"]),
        (
            set_in("camera_pose.encoding", "raw-depth-mm"),
            ErrorCode.invalid_field,
            ["field 'camera_pose.encoding' must be"],
        ),
    ],
)
def test_raw_depth_mm_rejects_malformed_buffers(
    mutate: Callable[[dict], None], code: ErrorCode, fragments: list[str]
) -> None:
    rejects(reframe(mm_frame(), mutate), code, *fragments)


def test_raw_depth_mm_truncated_buffer() -> None:
    frame = mm_frame()
    header_len = PREFIX.unpack_from(frame)[2]
    depth = json.loads(frame[PREFIX.size : PREFIX.size + header_len])["fields"]["depth"]
    cut = frame[: PREFIX.size + header_len + depth["offset"] + depth["nbytes"] - 1]
    rejects(cut, ErrorCode.malformed, "truncated", "field 'depth'")


def test_agent_sees_the_same_points_within_a_millimetre() -> None:
    """What the agent's mapping makes of mm depth: the same pixels, points within 1 mm."""
    from tidee.agent.mapping.geometry import unproject

    rng = np.random.default_rng(5)
    obs = observation(64)
    obs.depth[:] = rng.uniform(0.03, 12.0, (64, 64)).astype(np.float32)
    obs.depth[:2] = 0.0  # no return
    pose = np.eye(4)
    pose[:3, 3] = (0.2, -0.3, 0.9)
    obs = dataclasses.replace(obs, camera_pose=pose)
    out = decode(mm_frame(obs))
    assert isinstance(out.depth, np.ndarray) and out.depth.dtype == np.float32
    exact, exact_pix = unproject(obs.depth, obs.intrinsics, obs.camera_pose)
    got, got_pix = unproject(out.depth, out.intrinsics, out.camera_pose)
    # Only a depth within 0.5 mm of the 0.05 m / 10 m cut-offs can cross one; the rest map alike.
    flipped = np.setxor1d(exact_pix, got_pix)
    near_cut = np.minimum(np.abs(obs.depth.ravel() - 0.05), np.abs(obs.depth.ravel() - 10.0)) <= 0.0005
    assert near_cut[flipped].all()
    both, i, j = np.intersect1d(exact_pix, got_pix, return_indices=True)
    rays = np.linalg.norm(exact[i] - pose[:3, 3], axis=1) / obs.depth.ravel()[both]
    assert (np.linalg.norm(got[j] - exact[i], axis=1) <= 0.0005 * rays + 1e-5).all()


def test_a_large_memory_decodes_alike_in_threads_planning_at_once() -> None:
    import threading

    from tidee.protocol import codec
    from tidee.protocol.messages import ObjectMemoryMsg, TrackedObjectMsg

    rng = np.random.default_rng(0)
    objects = [
        TrackedObjectMsg(
            i,
            "Mug",
            float(rng.random()),
            tuple(map(float, rng.random(3))),
            tuple(map(float, rng.random(3) - 1)),
            tuple(map(float, rng.random(3) + 1)),
            float(rng.random()) if i % 2 else None,
            bool(i % 3 == 0),
            False,
            tuple(map(float, rng.random(3))) if i % 4 == 0 else None,
        )
        for i in range(200)
    ]
    msg = ObjectMemoryMsg("s", 7, objects)
    frame = encode(msg)
    codec._plan.cache_clear()  # every thread below finds the plans unmade
    out: list[Any] = []
    threads = [threading.Thread(target=lambda: out.append(decode(frame))) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(out) == 4 and all(m == msg for m in out)
    objects[3] = dataclasses.replace(objects[3], centroid=(1.0, 2.0))  # type: ignore[arg-type]
    with pytest.raises(ProtocolError, match=r"field 'objects\[3\]\.centroid' must be a list of 3 items"):
        decode(encode(ObjectMemoryMsg("s", 7, objects)))
