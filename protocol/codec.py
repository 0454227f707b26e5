"""Protocol messages <-> bytes.

Frame layout (all integers little-endian; see protocol/README.md)::

    offset 0   4 bytes   magic b"TIDE"
    offset 4   u16       protocol version (PROTOCOL_VERSION)
    offset 6   u32       header length H
    offset 10  H bytes   header: UTF-8 JSON {"type": <message name>, "fields": {...}},
                         right-padded with spaces so the buffer section starts 16-aligned
    offset 10+H          buffer section: the arrays' bytes

Plain fields are JSON (enums as their values, nested dataclasses as objects, tuples as
lists). An array field's JSON value is a descriptor
``{"dtype": "<f4", "shape": [h, w], "encoding": "raw", "offset": o, "nbytes": n}``:
``n`` bytes at offset ``o`` of the buffer section. ``raw`` arrays decode zero-copy with
``np.frombuffer`` (read-only views of the frame); ``encoding="png"|"jpeg"`` compresses
``Observation.rgb`` with opencv and sends ``Observation.depth`` as a 16-bit PNG in
millimetres (``png-depth-mm``). ``raw_depth="mm"`` sends a raw frame's depth maps as
uint16 millimetres (``raw-depth-mm``: half the bytes of float32, 1 mm precision); they
decode to float32 metres like every depth map. A simulation server does that when started
with ``TIDEE_WIRE_DEPTH=mm`` (``wire_depth()``; default ``f32``: exact).

Decoding is strict: any problem raises ``ProtocolError(code, message)`` with the field's
dotted path in the message; ``__post_init__`` validation of the dataclasses surfaces as
``ErrorCode.invalid_field``.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import inspect
import json
import math
import os
import struct
import types
import typing
from dataclasses import dataclass
from typing import Any

import numpy as np

from tidee.protocol import messages
from tidee.protocol.messages import IMAGE_ENCODINGS, PROTOCOL_VERSION, ErrorCode

MAGIC = b"TIDE"
_PREFIX = struct.Struct("<4sHI")
ALIGN = 16
DEFAULT_MAX_BYTES = 64 * 1024 * 1024
DEFAULT_JPEG_QUALITY = 90
_INT64 = (-(1 << 63), 1 << 63)

# How a raw frame's depth maps (ArraySpec image "depth") travel: "f32" float32 metres (the
# ``raw`` buffer encoding: exact, zero-copy decode) or "mm" uint16 millimetres
# (``raw-depth-mm``: half the bytes; 1 mm precision, 0 = no return, clamped at 65.535 m).
RAW_DEPTH_FORMS = ("f32", "mm")
DEPTH_MM = "raw-depth-mm"
WIRE_DEPTH_ENV = "TIDEE_WIRE_DEPTH"
DEFAULT_WIRE_DEPTH = "f32"  # mm flips a few map cells at their edges: opt in

# Every dataclass in messages.py can be a frame's top-level message.
MESSAGE_TYPES: dict[str, type] = {
    name: cls
    for name, cls in inspect.getmembers(messages, inspect.isclass)
    if dataclasses.is_dataclass(cls) and cls.__module__ == messages.__name__
}

_WIRE_DTYPES = frozenset({"|u1", "|i1", "|b1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f4", "<f8"})


class ProtocolError(Exception):
    """A frame that cannot be accepted; ``code`` says which kind of problem."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(f"{ErrorCode(code).value}: {message}")
        self.code = ErrorCode(code)
        self.message = message


# --- per-field array contracts ----------------------------------------------------------


@dataclass(frozen=True)
class ArraySpec:
    """What an array field must be: its dtype, rank, fixed dims, and image kind."""

    dtype: str  # numpy dtype.str on the wire
    shape: tuple[int | None, ...]  # None: any size
    image: str | None = None  # "color" | "depth": compressible under png/jpeg

    def describe(self) -> str:
        dims = "x".join("N" if d is None else str(d) for d in self.shape)
        return f"{np.dtype(self.dtype).name} {dims}"

    def matches(self, dtype: str, shape: tuple[int, ...]) -> bool:
        return (
            dtype == self.dtype
            and len(shape) == len(self.shape)
            and all(want is None or want == got for want, got in zip(self.shape, shape))
        )


ARRAY_FIELDS: dict[tuple[type, str], ArraySpec] = {
    (messages.Observation, "rgb"): ArraySpec("|u1", (None, None, 3), image="color"),
    (messages.Observation, "depth"): ArraySpec("<f4", (None, None), image="depth"),
    (messages.Observation, "camera_pose"): ArraySpec("<f8", (4, 4)),
    (messages.Observation, "intrinsics"): ArraySpec("<f8", (3, 3)),
    (messages.GroundTruth, "instance_seg"): ArraySpec("<i4", (None, None)),
    (messages.AgentStatus, "trajectory"): ArraySpec("<f4", (None, 2)),
    (messages.AgentStatus, "path"): ArraySpec("<f4", (None, 2)),
    (messages.AgentFrame, "rgb"): ArraySpec("|u1", (None, None, 3), image="color"),
    (messages.AgentFrame, "depth"): ArraySpec("<f4", (None, None), image="depth"),
    (messages.AgentFrame, "camera_pose"): ArraySpec("<f8", (4, 4)),
    (messages.AgentFrame, "intrinsics"): ArraySpec("<f8", (3, 3)),
    (messages.MapSnapshot, "occupancy"): ArraySpec("|u1", (None, None)),
    (messages.MapSnapshot, "explored"): ArraySpec("|b1", (None, None)),
    (messages.MapSnapshot, "points"): ArraySpec("<f4", (None, 3)),
    (messages.MapSnapshot, "point_labels"): ArraySpec("<i2", (None,)),
    (messages.SearchHeatmap, "heatmap"): ArraySpec("<f4", (None, None)),
    (messages.SearchHeatmap, "points"): ArraySpec("<f4", (None, 2)),
}


# --- encode -----------------------------------------------------------------------------


class _Buffers:
    """The buffer section being assembled: 16-aligned chunks and their descriptors."""

    def __init__(self) -> None:
        self.chunks: list[bytes | memoryview] = []
        self.size = 0

    def add(self, data: bytes | memoryview, dtype: str, shape: tuple[int, ...], encoding: str) -> dict:
        pad = -self.size % ALIGN
        if pad:
            self.chunks.append(b"\0" * pad)
            self.size += pad
        desc = {
            "dtype": dtype,
            "shape": list(shape),
            "encoding": encoding,
            "offset": self.size,
            "nbytes": len(data),
        }
        self.chunks.append(data)
        self.size += len(data)
        return desc


def wire_depth() -> str:
    """The ``raw_depth`` a simulation server sends: ``TIDEE_WIRE_DEPTH``, ``f32`` (default) or ``mm``."""
    form = os.environ.get(WIRE_DEPTH_ENV, "").strip() or DEFAULT_WIRE_DEPTH
    if form not in RAW_DEPTH_FORMS:
        raise ValueError(f"{WIRE_DEPTH_ENV} must be one of {RAW_DEPTH_FORMS}, got {form!r}")
    return form


def encode(
    msg: Any,
    encoding: str = "raw",
    *,
    jpeg_quality: int = DEFAULT_JPEG_QUALITY,
    raw_depth: str = "f32",
) -> bytes:
    """One frame for ``msg`` (any message dataclass); ``encoding`` applies to images.

    ``raw_depth``: under ``encoding="raw"``, depth maps travel as ``"f32"`` (exact) or
    ``"mm"`` (uint16 millimetres, ``raw-depth-mm``); png/jpeg always send millimetres.
    """
    name = type(msg).__name__
    if MESSAGE_TYPES.get(name) is not type(msg):
        raise TypeError(f"cannot encode {name}: not a message type ({', '.join(sorted(MESSAGE_TYPES))})")
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"encoding must be one of {IMAGE_ENCODINGS}, got {encoding!r}")
    if raw_depth not in RAW_DEPTH_FORMS:
        raise ValueError(f"raw_depth must be one of {RAW_DEPTH_FORMS}, got {raw_depth!r}")
    if encoding == "raw" and raw_depth == "mm":
        encoding = DEPTH_MM  # internal: raw, with millimetre depth maps
    buffers = _Buffers()
    fields = _encode_dataclass(msg, "", buffers, encoding, jpeg_quality)
    header = json.dumps({"type": name, "fields": fields}, separators=(",", ":"), allow_nan=False).encode()
    header += b" " * (-(_PREFIX.size + len(header)) % ALIGN)
    return b"".join([_PREFIX.pack(MAGIC, PROTOCOL_VERSION, len(header)), header, *buffers.chunks])


def _encode_dataclass(obj: Any, path: str, buffers: _Buffers, encoding: str, quality: int) -> dict:
    out = {}
    for f in dataclasses.fields(obj):
        value, fpath = getattr(obj, f.name), _join(path, f.name)
        if isinstance(value, np.ndarray):
            out[f.name] = _encode_array(
                value, fpath, ARRAY_FIELDS.get((type(obj), f.name)), buffers, encoding, quality
            )
        elif dataclasses.is_dataclass(value):
            out[f.name] = _encode_dataclass(value, fpath, buffers, encoding, quality)
        else:
            out[f.name] = _plain(value, fpath)
    return out


_JSON_SCALARS = frozenset({bool, int, float, str, type(None)})  # exact types: an enum is not one
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}  # a dataclass's field names, by its type


def _plain(value: Any, path: str) -> Any:
    """A JSON-able copy of a plain value (enums, numpy scalars and small arrays unwrapped)."""
    t = type(value)
    if t in _JSON_SCALARS:
        return value
    if t is tuple or t is list:  # checked first: most values in a message are numbers or lists of them
        return [v if type(v) in _JSON_SCALARS else _plain(v, f"{path}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, enum.Enum):
        return value.value
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [v if type(v) in _JSON_SCALARS else _plain(v, f"{path}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        for k in value:
            if not isinstance(k, str):
                raise TypeError(f"field '{path}' has a non-string key {k!r}; JSON objects need string keys")
        return {k: _plain(v, _join(path, k)) for k, v in value.items()}
    if dataclasses.is_dataclass(value):
        out = {}
        names = _FIELD_NAMES.get(t)
        if names is None:
            names = _FIELD_NAMES[t] = tuple(f.name for f in dataclasses.fields(value))
        for name in names:
            v = getattr(value, name)
            out[name] = v if type(v) in _JSON_SCALARS else _plain(v, _join(path, name))
        return out
    raise TypeError(f"field '{path}' holds a {type(value).__name__}, which has no wire form")


def _encode_array(
    arr: np.ndarray, path: str, spec: ArraySpec | None, buffers: _Buffers, encoding: str, quality: int
) -> dict:
    arr = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))
    dtype = arr.dtype.str
    if dtype not in _WIRE_DTYPES:
        raise TypeError(f"field '{path}' has dtype {arr.dtype}; the wire carries {sorted(_WIRE_DTYPES)}")
    if spec is not None and not spec.matches(dtype, arr.shape):
        raise TypeError(f"field '{path}' must be {spec.describe()}, got {arr.dtype} {arr.shape}")
    if encoding in ("png", "jpeg") and spec is not None and spec.image == "color":
        ext = ".jpg" if encoding == "jpeg" else ".png"
        import cv2  # OpenCV loads with the first compressed image, not with the protocol

        params = [cv2.IMWRITE_JPEG_QUALITY, quality] if encoding == "jpeg" else []
        ok, buf = cv2.imencode(ext, cv2.cvtColor(arr, cv2.COLOR_RGB2BGR), params)
        if not ok:
            raise ValueError(f"opencv could not {encoding}-encode field '{path}'")
        return buffers.add(buf.reshape(-1).data, dtype, arr.shape, encoding)
    if encoding == DEPTH_MM and spec is not None and spec.image == "depth":
        return buffers.add(memoryview(depth_to_mm(arr)).cast("B"), dtype, arr.shape, DEPTH_MM)  # type: ignore[arg-type]
    if encoding != "raw" and spec is not None and spec.image == "depth":
        import cv2

        ok, buf = cv2.imencode(".png", depth_to_mm(arr))
        if not ok:
            raise ValueError(f"opencv could not png-encode field '{path}'")
        return buffers.add(buf.reshape(-1).data, dtype, arr.shape, "png-depth-mm")
    # numpy's stubs declare ndarray's buffer protocol (__buffer__) for Python >= 3.12 only.
    return buffers.add(memoryview(arr).cast("B"), dtype, arr.shape, "raw")  # type: ignore[arg-type]


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """float32 metres -> uint16 millimetres: rounded to the nearest mm (error <= 0.5 mm), 0 for
    no return (nan, +-inf, <= 0.5 mm), clamped at 65535 (65.535 m)."""
    with np.errstate(invalid="ignore", over="ignore"):
        mm = np.multiply(depth, np.float32(1000.0), dtype=np.float32)  # overflow: inf, clamped
        mm[~np.isfinite(depth)] = 0.0
        np.rint(mm, out=mm)
        np.clip(mm, 0.0, 65535.0, out=mm)
    return mm.astype("<u2")


def mm_to_depth(mm: np.ndarray) -> np.ndarray:
    """uint16 millimetres -> float32 metres (the float32 nearest to mm / 1000)."""
    return np.divide(mm, np.float32(1000.0), dtype=np.float32)


# --- decode -----------------------------------------------------------------------------


def decode(
    data: bytes | bytearray | memoryview,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    expected: type | tuple[type, ...] | None = None,
) -> Any:
    """The message in ``data``; ``ProtocolError`` if anything about it is wrong.

    ``expected``: the message type(s) acceptable here, checked before the fields are.
    Raw arrays in the result are read-only views of ``data``.
    """
    view = memoryview(data).cast("B")
    if len(view) > max_bytes:
        raise ProtocolError(ErrorCode.oversized, f"frame is {len(view)} bytes, the limit is {max_bytes}")
    if len(view) < _PREFIX.size:
        raise ProtocolError(
            ErrorCode.malformed, f"frame is {len(view)} bytes, shorter than the {_PREFIX.size}-byte prefix"
        )
    magic, version, header_len = _PREFIX.unpack_from(view)
    if magic != MAGIC:
        raise ProtocolError(ErrorCode.malformed, f"bad magic {bytes(magic)!r}, expected {MAGIC!r}")
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            ErrorCode.bad_version,
            f"frame has protocol version {version}, this side speaks {PROTOCOL_VERSION}",
        )
    body_start = _PREFIX.size + header_len
    if body_start > len(view):
        raise ProtocolError(
            ErrorCode.malformed,
            f"frame truncated: the header claims {header_len} bytes, "
            f"only {len(view) - _PREFIX.size} follow the prefix",
        )
    header = _parse_header(view[_PREFIX.size : body_start])
    cls = MESSAGE_TYPES.get(header["type"]) if isinstance(header["type"], str) else None
    if cls is None:
        raise ProtocolError(
            ErrorCode.malformed,
            f"unknown message type {header['type']!r}; known: {', '.join(sorted(MESSAGE_TYPES))}",
        )
    if expected is not None and not issubclass(cls, expected):
        names = " or ".join(t.__name__ for t in (expected if isinstance(expected, tuple) else (expected,)))
        raise ProtocolError(ErrorCode.malformed, f"expected {names}, got {cls.__name__}")
    fields = header["fields"]
    if not isinstance(fields, dict):
        raise ProtocolError(ErrorCode.malformed, f"header 'fields' must be an object, got {_show(fields)}")
    if "protocol_version" in fields and fields["protocol_version"] != PROTOCOL_VERSION:
        raise ProtocolError(
            ErrorCode.bad_version,
            f"field 'protocol_version' is "
            f"{_show(fields['protocol_version'])}, this side speaks "
            f"{PROTOCOL_VERSION}",
        )
    return _Decoder(view[body_start:], max_bytes).dataclass(fields, cls, "")


def _parse_header(raw: memoryview) -> dict:
    def reject_constant(name: str) -> None:
        raise ValueError(f"non-finite number {name} in header")

    try:
        header = json.loads(bytes(raw).decode("utf-8"), parse_constant=reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise ProtocolError(ErrorCode.malformed, f"header is not valid UTF-8 JSON: {e}") from None
    if not isinstance(header, dict) or set(header) != {"type", "fields"}:
        keys = sorted(header) if isinstance(header, dict) else type(header).__name__
        raise ProtocolError(
            ErrorCode.malformed, f"header must be an object with keys 'type' and 'fields', got {keys}"
        )
    return header


class _Decoder:
    """Type-directed conversion of header JSON into message objects, against one frame.

    Each (type hint, array spec) gets a conversion plan once (:func:`_plan`); decoding a message
    runs its plans, so a memory of a hundred tracked objects is not re-inspected field by field.
    """

    def __init__(self, body: memoryview, max_bytes: int) -> None:
        self.body, self.max_bytes = body, max_bytes

    def value(self, value: Any, hint: Any, path: str, array_spec: ArraySpec | None = None) -> Any:
        return _plan(hint, array_spec)(self, value, path)

    def dataclass(self, obj: dict, cls: type, path: str) -> Any:
        return _plan(cls, None)(self, obj, path)

    def array(self, desc: Any, path: str, spec: ArraySpec | None) -> np.ndarray:
        want = {"dtype", "shape", "encoding", "offset", "nbytes"}
        if not isinstance(desc, dict) or set(desc) != want:
            raise _invalid(path, f"an array descriptor with keys {sorted(want)}", desc)
        dtype, shape, enc, offset, nbytes = (
            desc[k] for k in ("dtype", "shape", "encoding", "offset", "nbytes")
        )
        if dtype not in _WIRE_DTYPES:
            raise _invalid(f"{path}.dtype", f"one of {sorted(_WIRE_DTYPES)}", dtype)
        if not (
            isinstance(shape, list)
            and len(shape) <= 8
            and all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
        ):
            raise _invalid(f"{path}.shape", "a list of at most 8 non-negative integers", shape)
        for key, v in (("offset", offset), ("nbytes", nbytes)):
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                raise _invalid(f"{path}.{key}", "a non-negative integer", v)
        shape_t = tuple(shape)
        if spec is not None and not spec.matches(dtype, shape_t):
            raise _invalid(path, spec.describe(), f"{np.dtype(dtype).name} {shape_t}")
        size = math.prod(shape_t) * np.dtype(dtype).itemsize
        if size > self.max_bytes:
            raise ProtocolError(
                ErrorCode.oversized,
                f"field '{path}' declares {shape_t} "
                f"{np.dtype(dtype).name}: {size} bytes, the limit is "
                f"{self.max_bytes}",
            )
        if offset + nbytes > len(self.body):
            raise ProtocolError(
                ErrorCode.malformed,
                f"frame truncated: field '{path}' needs buffer bytes "
                f"[{offset}, {offset + nbytes}), the frame has "
                f"{len(self.body)}",
            )
        buf = self.body[offset : offset + nbytes]
        if enc == "raw":
            if nbytes != size:
                raise ProtocolError(
                    ErrorCode.invalid_field,
                    f"field '{path}' declares {shape_t} "
                    f"{np.dtype(dtype).name} = {size} bytes "
                    f"but nbytes is {nbytes}",
                )
            return np.frombuffer(buf, dtype=dtype).reshape(shape_t)
        image = spec.image if spec is not None else None
        allowed = {"color": ("png", "jpeg"), "depth": ("png-depth-mm", DEPTH_MM)}.get(image or "", ())
        if enc not in allowed:
            raise _invalid(f"{path}.encoding", f"one of {['raw', *allowed]}", enc)
        if enc == DEPTH_MM:
            if nbytes != size // 2:
                raise ProtocolError(
                    ErrorCode.invalid_field,
                    f"field '{path}' declares {shape_t} uint16 millimetres ({DEPTH_MM}) = "
                    f"{size // 2} bytes but nbytes is {nbytes}",
                )
            return mm_to_depth(np.frombuffer(buf, dtype="<u2").reshape(shape_t))
        return _decode_image(buf, shape_t, image, path)


def _decode_image(buf: memoryview, shape: tuple[int, ...], image: str | None, path: str) -> np.ndarray:
    """A png/jpeg buffer back to the declared array, refusing any size other than declared."""
    dims = _image_dims(buf)
    if dims is None:
        raise ProtocolError(ErrorCode.invalid_field, f"field '{path}' is not a PNG or JPEG image")
    if dims != shape[:2]:
        raise ProtocolError(
            ErrorCode.invalid_field,
            f"field '{path}': the compressed image is {dims[0]}x{dims[1]}, declared {shape[:2]}",
        )
    import cv2  # OpenCV loads with the first compressed image, not with the protocol

    raw = np.frombuffer(buf, np.uint8)
    if image == "color":
        bgr = cv2.imdecode(raw, cv2.IMREAD_COLOR)
        if bgr is None or bgr.shape != shape:
            raise ProtocolError(
                ErrorCode.invalid_field, f"field '{path}' does not decode to a {shape} colour image"
            )
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    mm = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
    if mm is None or mm.dtype != np.uint16 or mm.shape != shape:
        raise ProtocolError(
            ErrorCode.invalid_field, f"field '{path}' does not decode to a {shape} 16-bit PNG"
        )
    return mm.astype(np.float32) * np.float32(0.001)


def _image_dims(buf: memoryview) -> tuple[int, int] | None:
    """(height, width) from a PNG or JPEG header, read before decompressing anything."""
    b = bytes(buf[:65536]) if len(buf) > 65536 else bytes(buf)
    if b[:8] == b"\x89PNG\r\n\x1a\n" and len(b) >= 24 and b[12:16] == b"IHDR":
        width, height = struct.unpack(">II", b[16:24])
        return height, width
    if b[:2] == b"\xff\xd8":
        i = 2
        while i + 9 <= len(b) and b[i] == 0xFF:
            marker, seg_len = b[i + 1], struct.unpack(">H", b[i + 2 : i + 4])[0]
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
                height, width = struct.unpack(">HH", b[i + 5 : i + 9])
                return height, width
            i += 2 + seg_len
    return None


# --- decoding plans -----------------------------------------------------------------------

_Plan = typing.Callable[["_Decoder", Any, str], Any]


@functools.cache
def _plan(hint: Any, spec: ArraySpec | None) -> _Plan:
    """How to check and convert a header value of type ``hint``: built once per hint."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return lambda d, v, p: v
    if origin in (typing.Union, types.UnionType):
        arms = [a for a in args if a is not type(None)]
        nullable = type(None) in args
        if len(arms) != 1:

            def unsupported(d: _Decoder, v: Any, p: str) -> Any:
                if v is None and nullable:
                    return None
                if v is None:
                    raise _invalid(p, "a value, not null", v)
                raise TypeError(f"unsupported union {hint} at '{p}'")  # not in messages.py

            return unsupported
        inner = _plan(arms[0], spec)

        def union(d: _Decoder, v: Any, p: str) -> Any:
            if v is None:
                if nullable:
                    return None
                raise _invalid(p, "a value, not null", v)
            return inner(d, v, p)

        return union
    plan = _plan_of(hint, origin, args, spec)
    not_null = f"{_describe(hint)}, not null"

    def checked(d: _Decoder, v: Any, p: str) -> Any:
        if v is None:
            raise _invalid(p, not_null, v)
        return plan(d, v, p)

    return checked


def _plan_of(hint: Any, origin: Any, args: tuple, spec: ArraySpec | None) -> _Plan:
    """The plan for a non-null value of ``hint`` (not a union)."""
    if hint is np.ndarray:
        return lambda d, v, p: d.array(v, p, spec)
    if origin is typing.Literal:  # one of a vocabulary (protocol/vocab.py), e.g. a room type
        vocabulary, kind = set(args), type(args[0])

        def literal(d: _Decoder, v: Any, p: str) -> Any:
            if type(v) is kind and v in vocabulary:
                return v
            raise _invalid(p, f"one of {list(args)}", v)

        return literal
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return _dataclass_plan(hint)
    if isinstance(hint, type) and issubclass(hint, enum.Enum):

        def member(d: _Decoder, v: Any, p: str) -> Any:
            try:
                return hint(v)
            except ValueError:
                raise _invalid(p, f"one of {[e.value for e in hint]}", v) from None

        return member
    if hint is bool:

        def boolean(d: _Decoder, v: Any, p: str) -> Any:
            if isinstance(v, bool):
                return v
            raise _invalid(p, "a boolean", v)

        return boolean
    if hint is int:

        def integer(d: _Decoder, v: Any, p: str) -> Any:
            if type(v) is int and _INT64[0] <= v < _INT64[1]:
                return v
            raise _invalid(p, "a 64-bit integer", v)

        return integer
    if hint is float:

        def number(d: _Decoder, v: Any, p: str) -> Any:
            t = type(v)
            if t is float:
                return v
            if t is int:
                return float(v)
            raise _invalid(p, "a number", v)

        return number
    if hint is str:

        def string(d: _Decoder, v: Any, p: str) -> Any:
            if type(v) is str:
                return v
            raise _invalid(p, "a string", v)

        return string
    if origin is tuple:
        items = [_plan(a, None) for a in args]
        n = len(args)

        def fixed(d: _Decoder, v: Any, p: str) -> Any:
            if type(v) is not list or len(v) != n:
                raise _invalid(p, f"a list of {n} items", v)
            return tuple(f(d, x, f"{p}[{i}]") for i, (f, x) in enumerate(zip(items, v)))

        if all(a is float for a in args):  # a point or a box corner: the common case, checked at once

            def floats(d: _Decoder, v: Any, p: str) -> Any:
                if type(v) is list and len(v) == n and all(type(x) is float for x in v):
                    return tuple(v)
                return fixed(d, v, p)

            return floats
        return fixed
    if origin is list:
        item = _plan(args[0], None)

        def sequence(d: _Decoder, v: Any, p: str) -> Any:
            if type(v) is not list:
                raise _invalid(p, "a list", v)
            return [item(d, x, f"{p}[{i}]") for i, x in enumerate(v)]

        return sequence
    if origin is dict:
        item = _plan(args[1], None)

        def mapping(d: _Decoder, v: Any, p: str) -> Any:
            if type(v) is not dict:
                raise _invalid(p, "an object", v)
            return {k: item(d, x, _join(p, k)) for k, x in v.items()}

        return mapping

    def unsupported(d: _Decoder, v: Any, p: str) -> Any:
        raise TypeError(f"unsupported field type {hint} at '{p}'")  # not in messages.py

    return unsupported


def _dataclass_plan(cls: type) -> _Plan:
    hints = _hints(cls)
    names = frozenset(hints)
    fields: list[tuple[str, bool, _Plan]] = []

    def build(d: _Decoder, obj: Any, path: str) -> Any:
        if not fields:  # planned on first use, not when planned: a message type may refer to itself
            fields[:] = [  # one assignment: a second thread planning at the same time changes nothing
                (
                    f.name,
                    f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING,
                    _plan(hints[f.name], ARRAY_FIELDS.get((cls, f.name))),
                )
                for f in dataclasses.fields(cls)
            ]
        if type(obj) is not dict:
            raise _invalid(path, f"an object ({cls.__name__})", obj)
        if not names.issuperset(obj):
            unknown = sorted(set(obj) - names)
            raise ProtocolError(
                ErrorCode.invalid_field,
                f"unknown field '{_join(path, unknown[0])}' in {cls.__name__} (fields: {', '.join(hints)})",
            )
        kwargs = {}
        for name, required, plan in fields:
            if name not in obj:
                if required:
                    raise ProtocolError(ErrorCode.invalid_field, f"field '{_join(path, name)}' is required")
                continue
            kwargs[name] = plan(d, obj[name], _join(path, name))
        try:
            return cls(**kwargs)
        except (ValueError, TypeError) as e:
            where = f"field '{path}'" if path else cls.__name__
            raise ProtocolError(ErrorCode.invalid_field, f"invalid {where}: {e}") from None

    return build


# --- helpers ----------------------------------------------------------------------------


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _describe(hint: Any) -> str:
    return getattr(hint, "__name__", str(hint))


def _invalid(path: str, expectation: str, value: Any) -> ProtocolError:
    return ProtocolError(ErrorCode.invalid_field, f"field '{path}' must be {expectation}, got {_show(value)}")
