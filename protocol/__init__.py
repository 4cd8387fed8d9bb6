"""The contract between every process of magic-recon (DESIGN section 4).

Public surface: the radio messages and streams (:mod:`protocol.messages`), the sensor frames
and driver contract (:mod:`protocol.sensors`), SE(2) helpers (:mod:`protocol.se2`), clocks,
the radio's configuration and grants, and :class:`ProtocolError`. The zenoh link lives in
:mod:`protocol.link` and is imported explicitly (``from protocol.link import Link``), so that
importing the contract does not start any networking code.
"""

from protocol import se2
from protocol.clock import Clock, ManualClock, ScaledClock, WallClock
from protocol.messages import STREAMS, Direction, Reliability, decode_frame, encode_frame
from protocol.radio import RadioConfig, RadioGrant
from protocol.wire import PROTOCOL_VERSION, ProtocolError

__all__ = [
    "PROTOCOL_VERSION",
    "STREAMS",
    "Clock",
    "Direction",
    "ManualClock",
    "ProtocolError",
    "RadioConfig",
    "RadioGrant",
    "Reliability",
    "ScaledClock",
    "WallClock",
    "decode_frame",
    "encode_frame",
    "se2",
]
