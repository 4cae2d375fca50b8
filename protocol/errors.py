"""Protocol errors: every problem with an incoming frame raises a ``ProtocolError`` naming the field."""

from __future__ import annotations


class ProtocolError(ValueError):
    """A frame that cannot be accepted.

    ``field`` is the dotted path of the culprit (e.g. ``body.keypoints``), ``reason`` the bare message.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(f"{field}: {message}" if field else message)
        self.field = field
        self.reason = message


class VersionError(ProtocolError):
    """The frame speaks another protocol version."""


class UnknownTypeError(ProtocolError):
    """The frame's ``type`` is not a message of this protocol version."""


class FieldError(ProtocolError):
    """A field is missing, unknown, of the wrong type, shape or dtype, too large, or not finite."""


class FrameTooLarge(ProtocolError):
    """The frame exceeds ``Limits.max_frame_bytes``."""
