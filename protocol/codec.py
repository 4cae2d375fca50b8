"""msgpack codec for protocol v5 (reads v1-v4, writes any of them) with validation on decode.

A frame is one msgpack map ``{"v": 4, "type": str, "seq": int, "body": {...}}``. numpy arrays travel
as msgpack ext type 1: ``dtype code (1 byte) | ndim (1 byte) | shape (ndim x uint32 LE) | raw bytes``,
so encoding is a memcpy and decoding is ``np.frombuffer`` (read-only, no copy). Every decoded frame is
validated: version, type, field names, types, dtypes, shapes, sizes against :class:`Limits`,
finiteness, rigid poses; anything wrong raises a :class:`ProtocolError` naming the field, and
nothing else ever escapes :func:`decode`.
"""

from __future__ import annotations

import math
import struct
from dataclasses import MISSING, fields, replace
from typing import Any, TypeVar

import msgpack
import numpy as np

from hivemap.protocol.errors import FieldError, FrameTooLarge, ProtocolError, UnknownTypeError, VersionError
from hivemap.protocol.fields import (
    as_int,
)
from hivemap.protocol.limits import PROTOCOL_VERSION, SUPPORTED_VERSIONS, Limits
from hivemap.protocol.messages import (
    MESSAGE_TYPES,
    Message,
)
from hivemap.protocol.validate import VALIDATORS

_ND_EXT = 1
_DTYPES: dict[int, np.dtype[Any]] = {
    1: np.dtype("<f4"),
    2: np.dtype("<f8"),
    3: np.dtype("u1"),
    4: np.dtype("<i8"),
    5: np.dtype("<i4"),
    6: np.dtype("<u4"),
}
_CODES = {dt: code for code, dt in _DTYPES.items()}
_MAX_NDIM = 3
DEFAULT_LIMITS = Limits()


def _pack_array(a: np.ndarray) -> msgpack.ExtType:
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    code = _CODES.get(np.dtype(dt))
    if code is None:
        raise TypeError(f"dtype {a.dtype} cannot travel in the protocol")
    if a.ndim > _MAX_NDIM:
        raise TypeError(f"arrays of {a.ndim} dimensions cannot travel in the protocol")
    head = struct.pack(f"<BB{a.ndim}I", code, a.ndim, *a.shape)
    return msgpack.ExtType(_ND_EXT, head + np.ascontiguousarray(a, dtype=dt).tobytes())


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return _pack_array(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _newer_fields(mtype: str, version: int) -> set[str]:
    """The fields of message type ``mtype`` that a frame of ``version`` cannot carry."""
    return {f for since, table in _FIELDS_SINCE.items() if since > version for f in table.get(mtype, ())}


def carries(version: int, mtype: str) -> bool:
    """Whether a frame of protocol ``version`` can carry message type ``mtype`` (a reader of an older
    version rejects a newer type outright, so a sender must not write it at all)."""
    return version >= _SINCE.get(mtype, 1)


M = TypeVar("M", bound=Message)


def downgrade(msg: M, version: int) -> M:
    """``msg`` with the fields newer than ``version`` back at their defaults (what a reader of that
    version cannot take: an optional field it never knew), so that ``encode(.., version=version)`` can
    write it."""
    newer = _newer_fields(msg.TYPE, version)
    if not newer:
        return msg
    defaults = {f.name: f.default for f in fields(msg) if f.name in newer}
    return replace(msg, **defaults)  # type: ignore[type-var]


def encode(msg: Message, seq: int, version: int = PROTOCOL_VERSION) -> bytes:
    """Encode one message as a frame of protocol ``version`` (default the current one). An older version
    leaves out the fields it does not know; they must be at their defaults (:func:`downgrade`)."""
    if version not in SUPPORTED_VERSIONS:
        raise ValueError(f"protocol version {version} not supported")
    if version < _SINCE.get(msg.TYPE, 1):
        raise ValueError(f"message type {msg.TYPE!r} needs protocol v{_SINCE[msg.TYPE]}")
    newer = _newer_fields(msg.TYPE, version)
    body = {}
    for f in fields(msg):
        value = getattr(msg, f.name)
        if f.name in newer:
            if value is not f.default:
                raise ValueError(f"{msg.TYPE}.{f.name} cannot travel in protocol v{version}")
            continue
        body[f.name] = value
    frame = {"v": version, "type": msg.TYPE, "seq": int(seq), "body": body}
    return msgpack.packb(frame, default=_default, use_bin_type=True)


def _ext_hook(code: int, data: bytes) -> Any:
    if code != _ND_EXT:
        raise ProtocolError(f"unknown msgpack ext type {code}", "frame")
    if len(data) < 2:
        raise ProtocolError("array header truncated", "frame")
    dcode, ndim = data[0], data[1]
    dt = _DTYPES.get(dcode)
    if dt is None:
        raise ProtocolError(f"unknown array dtype code {dcode}", "frame")
    if ndim > _MAX_NDIM:
        raise ProtocolError(f"array of {ndim} dimensions", "frame")
    head = 2 + 4 * ndim
    if len(data) < head:
        raise ProtocolError("array shape truncated", "frame")
    shape = struct.unpack_from(f"<{ndim}I", data, 2)
    count = math.prod(shape)
    if count * dt.itemsize != len(data) - head:
        raise ProtocolError(
            f"array shape {shape} x {dt.itemsize} bytes does not match {len(data) - head} data bytes", "frame"
        )
    return np.frombuffer(data, dtype=dt, offset=head, count=count).reshape(shape)


_FIELDS = {name: {f.name for f in fields(cls)} for name, cls in MESSAGE_TYPES.items()}
# per protocol version, the fields it added, which an older frame cannot have (its reader takes their
# defaults: a v1 keyframe is all mono, tracked well; a v3 correction carries no covariance, a v3 hello does
# not ask for team advisories)
_FIELDS_SINCE: dict[int, dict[str, set[str]]] = {
    2: {"hello": {"stereo_baseline"}, "keyframe": {"u_right", "odom_sigma"}},
    4: {"hello": {"team_advisories"}, "correction": {"pose_covariance", "covariance_kf_id"}},
    5: {"keyframe": {"track_sigma"}},
    6: {"pose_updates": {"points_follow"}},
    7: {"keyframe": {"intent_velocity"}, "team_advisory": {"half_height_m"}},
}
# message types a frame of an older version cannot carry
_SINCE = {"rendezvous": 3, "team_advisory": 4}
_REQUIRED = {
    name: {f.name for f in fields(cls) if f.default is MISSING and f.default_factory is MISSING}
    for name, cls in MESSAGE_TYPES.items()
}


def decode(frame: bytes, limits: Limits = DEFAULT_LIMITS) -> tuple[int, Message]:
    """Decode and validate one frame -> (seq, message). Raises only :class:`ProtocolError`."""
    _, seq, msg = decode_versioned(frame, limits)
    return seq, msg


def decode_versioned(frame: bytes, limits: Limits = DEFAULT_LIMITS) -> tuple[int, int, Message]:
    """:func:`decode`, also giving the frame's protocol version: (version, seq, message)."""
    if not isinstance(frame, bytes | bytearray | memoryview):
        raise ProtocolError(f"frame must be bytes, got {type(frame).__name__}", "frame")
    if len(frame) > limits.max_frame_bytes:
        raise FrameTooLarge(f"{len(frame)} bytes exceed the limit of {limits.max_frame_bytes}", "frame")
    try:
        obj = msgpack.unpackb(
            frame,
            raw=False,
            ext_hook=_ext_hook,
            strict_map_key=True,
            max_str_len=max(limits.max_string_len, limits.max_token_len) * 4,
            max_bin_len=0,
            max_array_len=64,
            max_map_len=64,
            max_ext_len=limits.max_frame_bytes,
        )
    except ProtocolError:
        raise
    except Exception as e:  # msgpack raises many types (ExtraData, ValueError, StackError, ...)
        raise ProtocolError(f"not a valid msgpack frame ({type(e).__name__}: {e})", "frame") from None
    if not isinstance(obj, dict):
        raise ProtocolError(f"frame must be a map, got {type(obj).__name__}", "frame")
    if set(obj) != {"v", "type", "seq", "body"}:
        raise ProtocolError(f"frame keys must be v, type, seq, body; got {sorted(map(str, obj))}", "frame")
    version = obj["v"]
    if isinstance(version, bool) or not isinstance(version, int) or version not in SUPPORTED_VERSIONS:
        raise VersionError(f"protocol version {version!r} not supported (this is v{PROTOCOL_VERSION})", "v")
    mtype = obj["type"]
    if not isinstance(mtype, str) or mtype not in VALIDATORS:
        raise UnknownTypeError(f"unknown message type {mtype!r}", "type")
    if version < _SINCE.get(mtype, 1):
        raise UnknownTypeError(
            f"message type {mtype!r} needs protocol v{_SINCE[mtype]}, frame is v{version}", "type"
        )
    seq = as_int(obj["seq"], "seq", 0, limits.max_seq)
    body = obj["body"]
    if not isinstance(body, dict):
        raise FieldError(f"expected a map, got {type(body).__name__}", "body")
    keys = set(body)
    unknown = keys - (_FIELDS[mtype] - _newer_fields(mtype, version))
    if unknown:
        raise FieldError(
            f"unknown field(s) {sorted(map(str, unknown))}", f"body.{sorted(map(str, unknown))[0]}"
        )
    missing = _REQUIRED[mtype] - keys
    if missing:
        raise FieldError("missing", f"body.{sorted(missing)[0]}")
    try:
        return version, seq, VALIDATORS[mtype](body, limits)
    except ProtocolError:
        raise
    except Exception as e:  # defensive: a validator bug must still surface as a protocol error
        raise FieldError(f"invalid ({type(e).__name__}: {e})", "body") from None
