"""Decoding a CAN trace into the UCoM conversation it carries (``ucom decode``).

:func:`decode_frames` takes python-can messages (read from any log python-can reads, or
recorded by a test) and returns a :class:`Conversation`: per bus (the frames' channel;
frames without one are bus ``CAN``) and per board the messages in the order they were
on the bus, each decoded with the project's codecs (``man/ucom-protocol.7``), and the
protocol violations found on the way.  Pure: the result depends on the frames alone
(and on the attribute trees, when given).

What the conversation shows beyond single frames:

- multi-frame answers assembled: the 10 Info frames into one record, Text reports into
  their message, MCA DumpIO Descr segments into the edge's record;
- programming as progress: one line per BLOCK frame with the data frames that followed
  it (slots, and resends of frames already seen), a summary at each END;
- the run time with names: with the robot's attribute trees (:func:`load_trees`) MCA
  values carry their robot-wide unique names; values are decoded with the edge records
  seen in the trace (MCA DumpIO Descr), else with the program the board's tree maps;
  process-data maps are learned from the Admin Data SO_MAP/CI_MAP frames of the trace;
  cyclic frames (SO and CI maps, MCA Alive) are summarised per map.

The rules checked (:data:`RULES`): every frame decodes (a FrameError names the field);
every request a board answers is answered, and within the board's time of TIMEOUTS
(``ucom_tools.protocol.timeouts``) plus the wire time of the frames on the bus in
between, doubled as the host's deadlines double it, plus ``margin``; programming data
frames come in sequence (a slot inside the block the last BLOCK frame opened, rising);
an SO map keeps arriving at its period while its board's exchange runs.

As a library (a test that recorded its frames with a dispatcher tap)::

    conv = decode_frames(frames, load_trees(["armar3"]))
    assert conv.ok, conv.render(timeline=True)   # the decoded trace, readable
"""


from __future__ import annotations

import math
import typing
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import can

from ucom_tools.config.attrtree.robot import RobotTrees
from ucom_tools.errors import FrameError, InputError
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.trace.boot import BootDecoding
from ucom_tools.trace.bus import Decoder
from ucom_tools.trace.conversation import (
    BOARD_TO_PC,
    PC_TO_BOARD,
    RULES,
    BusConversation,
    Conversation,
    Message,
    Violation,
)
from ucom_tools.trace.logs import DEFAULT_BUS, channel_names, read_trace
from ucom_tools.trace.program import (
    ProgramDecoding,
)
from ucom_tools.trace.runtime import (
    RuntimeDecoding,
)
from ucom_tools.trace.state import (
    BACKWARDS_S,
    DEFAULT_MARGIN,
    TracedBoard,
)
from ucom_tools.trace.text import (
    _to,
    jsonable,
    raw_text,
)
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    ReadyReason,
)
from ucom_tools.wire.ids import Address, Direction, Function, IdType, function_direction
from ucom_tools.wire.info import INFO_FRAMES


class BusDecoder(BootDecoding, ProgramDecoding, RuntimeDecoding):
    """One bus's frames in bus order: each frame to the part that reads it."""

    # ------------------------------------------------------------------ frames
    def feed(self, index: int, msg: can.Message, t: float) -> None:
        self.index, self.t, self.raw = index, t, raw_text(msg)
        self.last_t = max(self.last_t, t)
        self.conv.frames += 1
        if msg.is_error_frame:
            self.add("bus", "error frame", "an error frame on the bus")
            return
        if msg.is_extended_id or msg.is_remote_frame or msg.is_fd:
            what = ("an extended-identifier" if msg.is_extended_id else
                    "a remote" if msg.is_remote_frame else "a CAN FD")
            self.add("bus", "foreign frame", f"{what} frame {self.raw}")
            self.violation("foreign-frame", f"{what} frame {self.raw}: the protocol uses "
                           "CAN 2.0A data frames with 11-bit identifiers only", "bus")
            return
        data = bytes(msg.data)
        self.pos += 1
        code = msg.arbitration_id >> 6
        direction = function_direction(code)
        if direction is Direction.HOST_TO_BOARD:
            self.horizon = max(self.horizon, t) + self.frame_time[min(len(data), 8)]
        board = self._label(msg.arbitration_id, direction, len(data))
        self.ids.append(msg.arbitration_id)
        self.wire.append(self.frame_time[min(len(data), 8)])
        self.senders.append("PC" if direction is Direction.HOST_TO_BOARD else board)
        address: Address
        message: object
        try:
            if code in m.BOOTLOADER_FUNCTIONS:
                address, message = m.decode(msg.arbitration_id, data)
            elif code in mca.MCA_FUNCTIONS:
                mca_address, message = mca.decode(msg.arbitration_id, data)
                address = mca_address or Address(IdType.FIXED, msg.arbitration_id & 0x1F)
            else:
                raise FrameError("function", f"code {code} is unassigned")
        except FrameError as err:
            name = Function(code).label if code <= 27 else f"function {code}"
            arrow = {Direction.HOST_TO_BOARD: PC_TO_BOARD,
                     Direction.BOARD_TO_HOST: BOARD_TO_PC}.get(direction, "-")
            self.add(board, name, f"malformed {self.raw}: {err}", {"field": err.field,
                     "error": err.message}, direction=arrow)
            self.violation("malformed", f"{name} {self.raw}: {err.field}: {err.message}",
                           board)
            return
        if direction is Direction.HOST_TO_BOARD:
            self._host(board, address, message)
        else:
            self._from_board(board, address, message)

    def _label(self, arbitration_id: int, direction: Direction, dlc: int) -> str:
        code, number, fixed = arbitration_id >> 6, arbitration_id & 0x1F, \
            bool(arbitration_id & 0x20)
        if code == Function.PROGRAM and dlc == 8:
            return "all"  # a data frame's low bits are its slot, not a board
        if fixed and code == Function.MCA_SENSOR_OUTPUT:
            return f"SO map {number}"
        if fixed and code == Function.MCA_CONTROLLER_INPUT:
            return f"CI map {number}"
        if number == 0 and not fixed:
            return "all" if direction is not Direction.BOARD_TO_HOST else "unnumbered"
        return f"F{number}" if fixed else str(number)


    def finish(self) -> None:
        """The trace ended: requests still waiting, maps that stopped."""
        self.t = self.last_t
        for e in self.expects:
            if not e.done:
                self.close(e, "the trace ends")
        for b in self.boards.values():
            self._flush_partial(b)
        for so in self.so_maps.values():
            self._check_map_end(so, self.last_t)
        self._summarise()

    # ------------------------------------------------------------------ requests
    # ------------------------------------------------------------------ dispatch
    def _host(self, board: str, address: Address, message: object) -> None:
        """A request from the PC, to the part that reads it (:data:`HOST`, by type)."""
        target = None if board == "all" else board
        read = HOST.get(type(message))
        if read is None:
            self._mca_request(board, target, message)  # the MCA requests, by function
        else:
            read(self, board, target, message)

    def _reset_request(self, board: str, target: str | None, message: m.Reset | m.XReset
                       ) -> None:
        label = Function(message.FUNCTION).label
        self.add(board, label, "", direction=PC_TO_BOARD)
        self._reset(target)
        self.expect(f"{label}{_to(board)}", message.FUNCTION, target,
                    self.owner.timeouts.reset,
                    lambda _b, a: isinstance(a, m.Ready) and a.reason is ReadyReason.BOOT)

    def _info_request(self, board: str, target: str | None, message: m.InfoRequest
                      ) -> None:
        self.add(board, Function.INFO_REQUEST.label,
                 "" if target else "every board with a number", direction=PC_TO_BOARD)
        self.expect(f"Info Request{_to(board)}", Function.INFO_REQUEST, target,
                    self.owner.timeouts.reply, lambda _b, a: isinstance(a, m.InfoFrame),
                    needed=INFO_FRAMES)

    def _from_board(self, board: str, address: Address, message: object) -> None:
        """A board's frame, to the part that reads it (:data:`FROM_BOARD`, by type); a
        single-frame answer is described, changes what is known of the board, and
        answers its request."""
        if isinstance(message, mca.MapFrame):
            self._so_map(board, message)
            return
        bd = self.board(board)
        read = FROM_BOARD.get(type(message))
        if read is not None:
            read(self, bd, message)
            return
        fn = Function(message.FUNCTION)  # type: ignore[attr-defined]
        text, fields_ = self._describe(bd, message)
        self.add(board, fn.label, text, fields_, direction=BOARD_TO_PC)
        itself = bd.resets_itself and isinstance(message, m.Ready) and \
            message.reason is ReadyReason.BOOT
        self._state_of(bd, message)
        if not itself:  # after VERSION_MISMATCH the board resets unasked
            self.answer(board, message)


def _program_frame(d: BusDecoder, board: str, target: str | None, message: Any) -> None:
    d._program(message, target)


HOST: dict[type, Callable[[BusDecoder, str, str | None, Any], None]] = {
    **{kind: _program_frame for kind in typing.get_args(m.ProgramFrame)},
    m.Reset: BusDecoder._reset_request,
    m.XReset: BusDecoder._reset_request,
    m.SetStatus: BusDecoder._set_status,
    m.InfoRequest: BusDecoder._info_request,
    m.ReportRequest: BusDecoder._report_request,
    m.InitRequest: lambda d, _board, _target, msg: d._init_request(msg),
    m.Start: BusDecoder._start,
}
"""Who reads which request of the PC (the rest are MCA requests: ``_mca_request``)."""

FROM_BOARD: dict[type, Callable[[BusDecoder, TracedBoard, Any], None]] = {
    m.Error: BusDecoder._error,
    m.InitAck: BusDecoder._init_ack,
    m.InfoFrame: BusDecoder._info,
    m.TextReport: BusDecoder._text,
    mca.DescrSegment: BusDecoder._segment,
}
"""Who reads which multi-frame or stateful answer of a board (the rest: ``_describe``)."""

def decode_frames(frames: Iterable[can.Message], trees: RobotTrees | None = None, *,
                  bitrate: int | None = None, margin: float = DEFAULT_MARGIN,
                  timeouts: Timeouts = DEFAULT) -> Conversation:
    """Decode a trace into its :class:`Conversation`.

    ``frames`` in trace order (a python-can reader, or a list); each bus's frames are
    read in timestamp order (a recording may write a sent frame after a received one
    that came later), the trace order breaking ties.  ``trees`` (:func:`load_trees`)
    names values and binds boards to their programs; ``bitrate`` (default: the
    topology's bus bitrate, else 1 Mbit/s) and ``margin`` (seconds) go into every answer
    deadline, with ``timeouts`` (the boards' times, TIMEOUTS)."""
    decoder = Decoder(trees, bitrate, margin, timeouts)
    listed = list(frames)
    start = min((f.timestamp for f in listed), default=None)
    per_bus: dict[str, list[tuple[int, can.Message]]] = {}
    names = channel_names({f.channel for f in listed},
                          [b.name for b in trees.topology.buses] if trees is not None else [])
    for i, f in enumerate(listed):
        per_bus.setdefault(names[f.channel], []).append((i, f))
    buses: list[BusConversation] = []
    for name, items in per_bus.items():
        _check_time_base(decoder, name, items, max(margin, BACKWARDS_S), start)
        items.sort(key=lambda x: (x[1].timestamp, x[0]))
        bus = BusDecoder(decoder, name)
        assert start is not None
        for i, f in items:
            bus.feed(i, f, f.timestamp - start)
        bus.finish()
        buses.append(bus.conv)
    decoder.violations.sort(key=lambda v: (v.index, v.rule))
    return Conversation(buses, decoder.violations, len(listed), start)


def _check_time_base(decoder: Decoder, bus: str, items: list[tuple[int, can.Message]],
                     margin: float, start: float | None) -> None:
    """One ``time-backwards`` violation for a bus whose frames, in the order they were
    written, run back by more than ``margin`` (a recording keeps one clock: a sent frame
    may be written a little after a received one that came later, no more)."""
    latest = -math.inf
    back = 0
    first: tuple[int, can.Message, float] | None = None
    for i, f in items:
        if f.timestamp < latest - margin:
            back += 1
            if first is None:
                first = (i, f, latest - f.timestamp)
        latest = max(latest, f.timestamp)
    if first is not None:
        i, f, by = first
        decoder.violations.append(Violation(
            f.timestamp - (start or 0.0), i, bus, "-", "time-backwards",
            f"frame {i} is stamped {by:.6f} s before a frame written before it"
            + (f" ({back} such frames)" if back > 1 else "")
            + "; the trace mixes time bases"))


def bus_name(channel: Any, trees: RobotTrees | None = None) -> str:
    """The bus a frame's channel names (:func:`~ucom_tools.trace.logs.channel_names`,
    the one rule for reading and writing; for a single channel, without the rule's
    look at the whole trace)."""
    buses = [b.name for b in trees.topology.buses] if trees is not None else []
    return channel_names([channel], buses)[channel]



def load_trees(args: Sequence[str]) -> RobotTrees:
    """The attribute trees of ``args``: one robot (a bundled topology name or a topology
    file whose boards name their trees) and/or tree files (``*.tree``), which replace the
    robot's blocks of the same Prefix; InputError (TreeError, TopologyError) otherwise."""
    from ucom_tools.config import topology as topo
    from ucom_tools.config.attrtree.robot import bind, with_files

    files = [a for a in args if a.endswith(".tree")]
    robots = [a for a in args if not a.endswith(".tree")]
    if len(robots) != 1:
        raise InputError("give one robot (a bundled topology such as armar3, or a topology "
                         "file naming its boards' trees)" + (f", not {len(robots)}: "
                                                             f"{', '.join(robots)}"
                                                             if robots else ""),
                         key="trees")
    return with_files(bind(topo.load(robots[0])), files)


__all__ = ["BOARD_TO_PC", "DEFAULT_BUS", "PC_TO_BOARD", "RULES", "BusConversation",
           "Conversation", "Message", "Violation", "bus_name", "decode_frames", "jsonable",
           "load_trees", "raw_text", "read_trace"]

