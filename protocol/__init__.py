"""Wire protocol v1: message dataclasses, msgpack codec, validation (numpy + msgpack only).

from hivemap.protocol import Keyframe, encode, decode
frame = encode(msg, seq)
seq, msg = decode(frame)  # raises ProtocolError (naming the field) on anything wrong
"""

from hivemap.protocol.codec import decode, encode
from hivemap.protocol.errors import FieldError, FrameTooLarge, ProtocolError, UnknownTypeError, VersionError
from hivemap.protocol.limits import PROTOCOL_VERSION, Limits
from hivemap.protocol.messages import (
    MESSAGE_TYPES,
    Ack,
    Bye,
    Correction,
    Error,
    Hello,
    Keyframe,
    MapPoints,
    Message,
    PoseUpdates,
    Welcome,
)

__all__ = [
    "MESSAGE_TYPES",
    "PROTOCOL_VERSION",
    "Ack",
    "Bye",
    "Correction",
    "Error",
    "FieldError",
    "FrameTooLarge",
    "Hello",
    "Keyframe",
    "Limits",
    "MapPoints",
    "Message",
    "PoseUpdates",
    "ProtocolError",
    "UnknownTypeError",
    "VersionError",
    "Welcome",
    "decode",
    "encode",
]
