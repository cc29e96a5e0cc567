"""CiA 301 codes the gateway's CANopen nodes speak: NMT states and commands, SDO abort
codes, the COB-ID bases of the pre-defined connection set, and the state-change message
handed to the application (``ucom_tools.gateway.node``)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class NmtState(IntEnum):
    """An NMT slave's state, as its heartbeat carries it (CiA 301, 7.2.8.3.2.1)."""

    INITIALISING = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class NmtCommand(IntEnum):
    """The command specifier of an NMT frame (COB-ID 0x000: command, node ID or 0)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class SdoAbort(IntEnum):
    """SDO abort codes (CiA 301, table 22) this runtime answers with."""

    UNSUPPORTED_ACCESS = 0x06010000
    READ_ONLY = 0x06010002
    NO_OBJECT = 0x06020000
    NOT_MAPPABLE = 0x06040041
    PDO_LENGTH = 0x06040042
    INCOMPATIBLE = 0x06040043
    NO_SUBINDEX = 0x06090011
    VALUE_RANGE = 0x06090030
    VALUE_TOO_HIGH = 0x06090031
    VALUE_TOO_LOW = 0x06090032
    GENERAL = 0x08000000
    DEVICE_STATE = 0x08000022
    """"Data cannot be transferred or stored because of the present device state": a
    write to an edge of a board that is lost."""


class Cob(IntEnum):
    """Function codes of the pre-defined connection set (COB-ID = base + node ID)."""

    NMT = 0x000
    SYNC = 0x080
    EMCY = 0x080
    TPDO1 = 0x180
    RPDO1 = 0x200
    SDO_TX = 0x580
    SDO_RX = 0x600
    HEARTBEAT = 0x700


#: COB-ID bits of the PDO communication records' sub-index 1 (and of 0x1005/0x1014)
COB_INVALID = 1 << 31
COB_NO_RTR = 1 << 30
COB_29BIT = 1 << 29
COB_ID_MASK = 0x7FF


def restricted(cob_id: int) -> bool:
    """Whether an 11-bit identifier is one CiA 301 (table 3) reserves, never a PDO's."""
    return (cob_id <= 0x07F or 0x101 <= cob_id <= 0x180 or 0x581 <= cob_id <= 0x5FF
            or 0x601 <= cob_id <= 0x67F or 0x6E0 <= cob_id <= 0x7FF)


@dataclass(frozen=True)
class StateChange:
    """A node's NMT state changed: from ``old`` to ``new``, on ``command`` (``None``: the
    runtime's start).  A reset is two changes: to INITIALISING (with the reset command),
    then to PRE-OPERATIONAL after its boot-up (also with the reset command)."""

    node_id: int
    old: NmtState
    new: NmtState
    command: NmtCommand | None
