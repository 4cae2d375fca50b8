"""Wire protocol v5 (the versions: :mod:`hivemap.protocol.limits`): message dataclasses, msgpack codec,
validation (numpy + msgpack only).

from hivemap.protocol import Keyframe, encode, decode
frame = encode(msg, seq)
seq, msg = decode(frame)  # raises ProtocolError (naming the field) on anything wrong
frame = encode(downgrade(msg, 3), seq, version=3)  # to a peer that said hello in v3
carries(3, "team_advisory")  # False: a message type newer than the peer's version is not sent to it

Identity rules (missions and sessions). Data is keyed by (agent id, mission, session):

* A *mission* is one agent outbox: a UUID created with it and sent in every ``hello``. Seqs count 1, 2,
  3, ... within a mission; ``hello.resume_from`` and ``welcome.last_seq`` are that mission's.
* A *session* is one front-end map within a mission (``hello.session`` and every data message's
  ``session``); a tracking loss, or an agent process restarted on the same outbox, starts the next one.
  Session numbers only grow within a mission.
* A known agent id with a mission the server has not seen is a new mission: its sessions become new agent
  maps of that agent (stored, listed on REST, merged like any other map) and never touch the maps of the
  agent's earlier missions, whatever ids and seqs it reuses. A fresh outbox is always a new mission.
* ``welcome.mission_known`` is false when the server has no record of the mission; a resuming agent then
  sends its whole outbox again (outboxes keep acknowledged frames for that).
* A data message's seq may exceed the mission's last seen seq by at most the server's ``max_seq_step``.
* Corrections name the session they correct as the agent numbered it, and reach only that mission.
"""

from hivemap.protocol.codec import carries, decode, decode_versioned, downgrade, encode
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
    Rendezvous,
    TeamAdvisory,
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
    "Rendezvous",
    "TeamAdvisory",
    "UnknownTypeError",
    "VersionError",
    "Welcome",
    "carries",
    "decode",
    "decode_versioned",
    "downgrade",
    "encode",
]
