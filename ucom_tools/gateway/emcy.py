"""The EMCY producer of one gateway node, with the upkeep canopen's ``EmcyProducer``
leaves out: the error register 0x1001, the pre-defined error field 0x1003 (newest first,
as many as the dictionary's array holds; a master clears it by writing 0 to sub-index 0),
the EMCY COB-ID 0x1014 (bit 31: no EMCY is sent) and the inhibit time 0x1015 (100 us
units: EMCYs closer than that wait in order, none is dropped).

An EMCY goes out in PRE-OPERATIONAL and OPERATIONAL; in STOPPED it is recorded (0x1001,
0x1003) but not sent.  Code 0 is the error reset: 0x1001 takes the register given
(normally 0) and the history stays.
"""

from __future__ import annotations

import struct
from collections import deque

from canopen.objectdictionary import ODArray

from ucom_tools.gateway.codes import COB_ID_MASK, COB_INVALID, Cob

EMCY = struct.Struct("<HB5s")
U8 = struct.Struct("<B")
U32 = struct.Struct("<I")
ERROR_REGISTER, ERROR_FIELD, COB_ID_EMCY, INHIBIT_EMCY = 0x1001, 0x1003, 0x1014, 0x1015
GENERIC = 0x01  # the error register's bit set for every error


class EmcyProducer:
    """One node's EMCYs: :meth:`record` keeps the dictionary and queues the frame,
    :meth:`due` hands out the frames the inhibit time lets go."""

    def __init__(self, node_id: int, data_store: dict[int, dict[int, bytes]]) -> None:
        self.node_id = node_id
        self._store = data_store
        self.cob_id = Cob.EMCY + node_id
        self.enabled = True
        self.inhibit = 0.0
        self.history = 0  # how many entries 0x1003 holds (0: no 0x1003)
        self.queue: deque[bytes] = deque()
        self.next_time = float("-inf")

    def configure(self, cob_id: int | None, inhibit_100us: int, history: int) -> None:
        """Take 0x1014 (``None``: not in the dictionary), 0x1015 and 0x1003's size."""
        if cob_id is None:
            cob_id = Cob.EMCY + self.node_id
        self.enabled = not cob_id & COB_INVALID
        self.cob_id = cob_id & COB_ID_MASK
        self.inhibit = inhibit_100us * 1e-4
        self.history = history

    def record(self, code: int, register: int, data: bytes) -> None:
        """Keep an EMCY in 0x1001/0x1003 and queue its frame."""
        if not 0 <= code <= 0xFFFF:
            raise ValueError(f"EMCY code {code:#x}: 16 bits")
        if not 0 <= register <= 0xFF:
            raise ValueError(f"error register {register:#x}: 8 bits")
        if len(data) > 5:
            raise ValueError(f"EMCY data of {len(data)} bytes: at most 5")
        if code:
            register |= GENERIC
            self._push(code)
        self._store.setdefault(ERROR_REGISTER, {})[0] = U8.pack(register)
        self.queue.append(EMCY.pack(code, register, data))

    def _push(self, code: int) -> None:
        if not self.history:
            return
        field = self._store.setdefault(ERROR_FIELD, {})
        count = min(U8.unpack(field.get(0, b"\0"))[0], self.history)
        for sub in range(min(count, self.history - 1), 0, -1):
            field[sub + 1] = field.get(sub, U32.pack(0))
        field[1] = U32.pack(code)
        field[0] = U8.pack(min(count + 1, self.history))

    def clear_history(self) -> None:
        """0x1003 emptied (a master wrote 0 to its sub-index 0)."""
        field = self._store.get(ERROR_FIELD)
        if field is not None:
            for sub in list(field):
                if sub:
                    del field[sub]

    def due(self, now: float, send: bool, out: list[tuple[int, bytes]]) -> float:
        """Append the frames due at ``now`` to ``out`` (dropped where ``send`` is false:
        STOPPED, or 0x1014 invalid); the time the next one is due (inf: none queued)."""
        queue = self.queue
        if not (send and self.enabled):
            queue.clear()
            return float("inf")
        while queue and now >= self.next_time:
            out.append((self.cob_id, queue.popleft()))
            self.next_time = now + self.inhibit
            if self.inhibit > 0:
                break
        return self.next_time if queue else float("inf")


def history_size(array: object) -> int:
    """How many errors a 0x1003 array holds: its highest sub-index."""
    if not isinstance(array, ODArray):
        return 0
    return max((s for s in array.subindices if s), default=0)
