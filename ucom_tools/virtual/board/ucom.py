"""A virtual UCoM: the bootloader state machine of ``man/ucom-protocol.7`` as a bus node.

The board reacts to frames on its :class:`~ucom_tools.virtual.bus.simbus.SimBus` and
answers with real frames; it never shares state with the host.  Init pins, LEDs, flash
timing, AutoStart in non-volatile memory and volatile ExtRAM behave as in the dissertation
(B.2.2, B.2.3, B.3.1).

The board is composed of its memory (flash and bootloader record, the FPGA behind the X:
window), its bootloader's services (:mod:`~ucom_tools.virtual.board.bootloader`: the init
chain, Set Status, Info, the reports), its programming part
(:mod:`~ucom_tools.virtual.board.programming`) and the program it runs
(:mod:`~ucom_tools.virtual.board.application`); it hands itself to those parts as a
:class:`~ucom_tools.virtual.board.port.BoardPort`, so they never import this module.  This
module keeps power and reset, receiving and sending frames, and Start.  The plant behind
the board (motors, joints, sensors) is its hardware too: a program that starts again
drives the plant the last one left (:meth:`VirtualBoard.bind_plant`).

Injected faults (:mod:`~ucom_tools.virtual.injected` times them) act through
:meth:`VirtualBoard.lose_power` / :meth:`VirtualBoard.regain_power` (a power loss, a reset
of the DSP) and :meth:`VirtualBoard.enter_bus_off` / :meth:`VirtualBoard.leave_bus_off`
(its CAN controller off the bus).  A board that lost its seq ID is numbered again with
Init Request REJOIN (INIT CHAIN, Rejoin).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import ClassVar, Final

from ucom_tools.config.topology import Timing
from ucom_tools.errors import FrameError
from ucom_tools.plugons import PLUG_ON_BOARDS
from ucom_tools.virtual.board import mutants
from ucom_tools.virtual.board.application import DspProgram
from ucom_tools.virtual.board.bootloader import Bootloader
from ucom_tools.virtual.board.nvmem import NonVolatile
from ucom_tools.virtual.board.port import Identity
from ucom_tools.virtual.board.programming import BoardProgramming
from ucom_tools.virtual.bus.simbus import SimBus
from ucom_tools.virtual.hardware.fpga import ExternalMemory, VirtualFpga
from ucom_tools.virtual.programs.base import Plant
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.answers import AppReport
from ucom_tools.wire.codes import (
    BoardState,
    ErrorCode,
    ProgramOp,
    ReadyReason,
    Space,
    Target,
)
from ucom_tools.wire.descriptor import DESCRIPTOR_ADDRESS, DESCRIPTOR_WORDS, ImageDescriptor
from ucom_tools.wire.fpga import FpgaVersion
from ucom_tools.wire.ids import Address, Direction, Function, IdType, encode_id

_FROM_BOARD: Final = frozenset(f.value for f in Function if f.direction is Direction.BOARD_TO_HOST)
_MCA_FROM_HOST: Final = frozenset(f.value for f in Function
                                   if f.direction is Direction.HOST_TO_BOARD
                                   and f not in m.BOOTLOADER_FUNCTIONS)
_PROGRAM: Final = int(Function.PROGRAM)
_MCA_CI: Final = int(Function.MCA_CONTROLLER_INPUT)
_SET_STATUS: Final = int(Function.SET_STATUS)


class VirtualBoard:
    """One UCoM with its bootloader, on one bus, at one position of the init chain.

    ``defect`` makes it a mutant board: a defect of :mod:`~ucom_tools.virtual.board.mutants`
    (InputError for an unknown name), fixed for the board's life."""

    takes_board_frames: ClassVar[bool] = False
    """The bus offers a board no frame another board sent
    (:class:`~ucom_tools.virtual.bus.simbus.Node`): :meth:`on_frame` ignores each of them."""

    def __init__(self, bus: SimBus, identity: Identity, *, timing: Timing | None = None,
                 powered: bool = True, state_file: Path | None = None,
                 defect: str | None = None) -> None:
        self.bus = bus
        self.identity = identity
        self.defect = mutants.check(defect)
        """The documented defect this board has (None: it conforms)."""
        self.timing = timing or Timing()
        self.nv = NonVolatile()
        self.state_file = state_file
        if state_file is not None:
            self.nv.load(state_file)
        self._powered = False
        self._rx = False
        """The CAN controller passes frames to the software: powered and not bus-off (the
        one flag :meth:`on_frame` looks at)."""
        self._tx = False
        """The CAN controller sends: powered and not bus-off."""
        self.bus_off = False
        """The CAN controller is off the bus (an injected fault): it neither sends nor
        acknowledges; the program runs on."""
        self._epoch = 0
        """Counts the power losses: a reset timer of a life before one does nothing."""
        self.plant: Plant | None = None
        """The motors, joints and sensors behind the board (its hardware, kept across its
        programs and power losses); None until a program made one."""
        self._plant_t = 0.0
        """When a program last moved :attr:`plant`."""
        self.in_drive = False
        self.out_drive = False
        self.seq_id = 0
        self.programming = BoardProgramming(self, self.nv, defect=self.defect)
        self.bootloader = Bootloader(self, self.nv, self.programming, defect=self.defect)
        self.application: DspProgram | None = None
        self.stagger_us = (identity.serial & 0x3F) * bus.us_per_bit
        plug = PLUG_ON_BOARDS[identity.board].board_id
        self.fpga = VirtualFpga(identity.fpga or FpgaVersion(plug, 1, 1, 0), plug)
        self.xmem = ExternalMemory(self.fpga)
        self.adc = [0] * 8
        """The DSP's 8 ADC channels (12 bit), set by the plant of a running program."""
        self.can_errors = 0
        """Error frames this board's CAN controller saw."""
        self._suppress_autostart = False
        if powered:
            self.power_on(bus.now)

    # ================================================================= port and state
    @property
    def powered(self) -> bool:
        return self._powered

    @property
    def listening(self) -> bool:
        """The CAN controller takes (and acknowledges) frames: powered, not bus-off."""
        return self._rx

    @property
    def state(self) -> BoardState:
        """Derived from what the board does: a program, a transfer, or the bootloader."""
        app = self.application
        if app is not None:
            return (BoardState.RUNNING_EXTRAM if app.target is Target.EXTRAM
                    else BoardState.RUNNING_FLASH)
        return self.programming.state() or BoardState.BOOTLOADER

    @property
    def runs_program(self) -> bool:
        """A DSP program runs (the bootloader refuses what it may do only without one)."""
        return self.application is not None

    def application_report(self) -> AppReport | None:
        """The running program's report (channel APPLICATION); None without one."""
        app = self.application
        return app.runtime.report() if app is not None and app.runtime is not None else None

    @property
    def prog_enable(self) -> bool:
        return self.programming.enabled

    @property
    def overruns(self) -> int:
        return self.programming.overruns

    def at(self, t: float, callback: Callable[[float], None]) -> None:
        self.bus.at(t, callback)

    # ================================================================= power & reset
    def power_on(self, t: float) -> None:
        """Power-on: volatile state cleared, init outputs set (B.2.2 (b))."""
        self._powered = True
        self._rx = self._tx = not self.bus_off
        self.seq_id = 0
        self.bootloader.claimed = False
        if self.defect == mutants.AUTOSTART_LOST and self.nv.record.autostart:
            self.nv.record.autostart = False  # the flag did not survive the power cycle
            self.persist(record_only=True)
        self._boot(t)

    def power_off(self) -> None:
        """Power loss: flash keeps what was written; everything else is gone."""
        self._powered = False
        self._rx = self._tx = False
        self.fpga = VirtualFpga(self.fpga.config, self.fpga.plug_board_id)
        self.xmem = ExternalMemory(self.fpga)
        self._drop_volatile()
        self.in_drive = self.out_drive = False

    def _drop_volatile(self) -> None:
        """What a reset or a power loss takes away (the seq ID survives a reset)."""
        self.programming.drop(self.bus.now)
        self._end_application()
        self.bootloader.chain_active = False

    def _boot(self, t: float) -> None:
        self._drop_volatile()
        self.in_drive = False
        self.out_drive = True
        rec = self.nv.record
        if rec.autostart and rec.flash_valid and not self._suppress_autostart:
            self._start_program(Target.FLASH, t, announce=False)
        self._suppress_autostart = False

    def _reset(self, t: float, clear_autostart: bool) -> None:
        lost = self.defect == mutants.AUTOSTART_LOST  # the flag does not survive a reset
        if (clear_autostart or lost) and self.nv.record.autostart and \
                (self.defect != mutants.XRESET_KEEPS_AUTOSTART or lost):
            self.nv.record.autostart = False
            self.persist(record_only=True)
        self._end_application()
        self._after_reset_at(t + self.timing.reset_us)

    def _after_reset_at(self, t: float) -> None:
        """:meth:`_after_reset` at ``t``, unless the board lost power before."""
        epoch = self._epoch

        def after(when: float) -> None:
            if self._epoch == epoch:
                self._after_reset(when)
        self.bus.at(t, after)

    def _end_application(self) -> None:
        app = self.application
        if app is not None:
            if app.runtime is not None and app.runtime.plant is not None:
                self._plant_t = app.runtime.last_tick  # where the loop left the plant
            app.end()
            self.application = None
            self.filters_changed()

    def bind_plant(self, plant: Plant, t: float) -> None:
        """A program starts driving ``plant`` at ``t``: the board's plant from before is
        resumed over the time since a program last moved it (it coasted; after a power
        loss it is bound to the new FPGA, :meth:`Plant.resume`); a new one replaces it."""
        if plant is self.plant:
            plant.resume(self.fpga, self.adc, max(0.0, t - self._plant_t))
        self.plant = plant
        self._plant_t = t

    # ================================================================= injected faults
    def lose_power(self, t: float) -> None:
        """The board loses power at ``t`` (an injected fault; a reset of the DSP as well):
        silent at once - the frames its CAN controller still held are lost, one on the
        wire is cut short -, its RAM gone (program, exchange, seq ID, the FPGA's registers
        and counters), its LEDs off; flash and AutoStart stay.  The plant moved with the
        outputs as they were up to ``t``."""
        if not self._powered:
            return
        app = self.application
        if app is not None and app.runtime is not None:
            app.runtime.settle(t)
        self.bus.withdraw(self)
        self._epoch += 1
        self._suppress_autostart = False
        self.power_off()
        self.seq_id = 0
        self.bootloader.claimed = False

    def regain_power(self, t: float, *, announce: bool = False) -> None:
        """Power returns at ``t``: the board comes up as at power-on (:meth:`power_on`:
        its bootloader, or with AutoStart its program, STOPPED and unconfigured), with no
        seq ID, so it sends nothing until it is numbered again (REJOIN).  ``announce``
        (after a reset of the DSP): Ready BOOT, as after a Reset, where it has a fixed
        ID to send it with."""
        if self._powered:
            return
        self.power_on(t)
        if announce and self.reply_address() is not None:
            self.send(t, m.Ready(ReadyReason.BOOT, self.state, 0, self.identity.serial))

    def enter_bus_off(self) -> None:
        """The CAN controller goes bus-off (an injected fault): it neither sends nor
        acknowledges; what it held to send is lost, and so is what the program sends
        meanwhile.  The program runs on (its watchdog may fire); the red LED is lit."""
        self.bus_off = True
        self._rx = self._tx = False
        self.bus.withdraw(self)
        self.filters_changed()

    def leave_bus_off(self) -> None:
        """The CAN controller is error-active again."""
        self.bus_off = False
        self._rx = self._tx = self._powered
        self.filters_changed()

    def takes_ci_map(self, number: int) -> bool:
        """Whether the board's CAN controller passes CI map ``number`` on to its software
        (:class:`~ucom_tools.virtual.bus.simbus.Node`): while it is powered and its program's
        run time defined that map (and it is not bus-off).  :meth:`on_frame` would ignore
        every other CI map frame,
        at no cost to the program's load."""
        app = self.application
        return self._rx and number != 0 and app is not None and app.takes_ci_map(number)

    def filters_changed(self) -> None:
        """What :meth:`takes_ci_map` answers may have changed: the bus asks again."""
        self.bus.filters_changed()

    def running(self, program: object) -> bool:
        """Is ``program`` still the one this board runs (no reset or power loss since)?"""
        return self.application is program and self._powered

    def end_program(self, t: float, *, reset: bool) -> None:
        """The program ended (incompatible) or aborted with a reset (FPGA major)."""
        self._end_application()
        if reset:
            self._suppress_autostart = True
            self._after_reset_at(t + self.timing.reset_us)

    def _after_reset(self, t: float) -> None:
        if not self._powered:
            return
        self._boot(t)
        if self.reply_address() is not None:
            self.send(t, m.Ready(ReadyReason.BOOT, self.state, 0, self.identity.serial))

    # ================================================================= sending
    def reply_address(self, via_fixed: bool = False) -> Address | None:
        """The identifier this board answers with; None if it has no number yet."""
        fid = self.identity.fixed_id
        if via_fixed and fid:
            return Address(IdType.FIXED, fid)
        if self.seq_id:
            return Address(IdType.SEQUENTIAL, self.seq_id)
        if fid:
            return Address(IdType.FIXED, fid)
        return None

    def send(self, t: float, msg: m.BootMessage | mca.McaMessage, *, via_fixed: bool = False,
             address: Address | None = None) -> None:
        if not self._tx:
            return
        addr = address or self.reply_address(via_fixed)
        if addr is None:
            return
        self.bus.send(self, t, encode_id(msg.FUNCTION, addr), msg.encode())

    def send_raw(self, t: float, arbitration_id: int, data: bytes) -> None:
        if self._tx and (self.seq_id or self.identity.fixed_id):
            self.bus.send(self, t, arbitration_id, data)

    def report_text(self, t: float, text: str) -> None:
        for frame in m.text_reports(text):
            self.send(t, frame)

    def error(self, t: float, code: ErrorCode, function: int, detail: int = 0,
              via_fixed: bool = False) -> None:
        self.send(t + self.timing.reply_us, m.Error(code, function, detail), via_fixed=via_fixed)

    # ================================================================= receiving
    @property
    def placement(self) -> str:
        return self.identity.placement

    def on_bus_error(self, t: float) -> None:
        """An error frame on the bus: the CAN controller's error counter (a running
        program shows it on the red LED)."""
        if not self._rx:
            return
        self.can_errors += 1
        if self.application is not None and self.application.runtime is not None:
            self.application.runtime.can_error(t)

    def on_extended_frame(self, arbitration_id: int, data: bytes, t: float) -> None:
        """An extended frame (29-bit identifier) on the bus: not part of the protocol
        (man/ucom-protocol.7, BUS), so the board ignores it, whatever its identifier's
        bits would mean in an 11-bit one: no answer, no Error, no state change."""

    def on_frame(self, arbitration_id: int, data: bytes, t: float) -> None:
        if not self._rx:
            return
        function = arbitration_id >> 6
        if function == _PROGRAM and len(data) == 8:
            # a data frame: no address; bits 5-0 are its slot in the current block, which
            # only a BLOCK frame addressed to this board (or broadcast) opens
            if self.programming.reception is not None and self.application is None:
                self.programming.data(arbitration_id & 0x3F, data, t)
            return
        if function in _FROM_BOARD:
            return  # another board's traffic
        id_type, number = (arbitration_id >> 5) & 1, arbitration_id & 0x1F
        if function in _MCA_FROM_HOST and id_type == 1:
            # run time: type 1 is process data, map ``number`` (only CI maps come from
            # the PC); the program knows which maps it takes
            if function == _MCA_CI and number and self.application is not None:
                self.application.on_map(number, data, t)
            return
        if id_type == 0:
            broadcast = number == 0
            mine = broadcast or number == self.seq_id
            via_fixed = False
        else:
            broadcast = False
            mine = bool(self.identity.fixed_id) and number == self.identity.fixed_id
            via_fixed = True
        if not mine and not (function == _SET_STATUS and id_type == 0
                             and self.defect == mutants.PROMISCUOUS):
            if function == _PROGRAM and data and data[0] == ProgramOp.BLOCK:
                self.programming.other_block()
            return
        if function > 27:
            if not broadcast and self.defect != mutants.UNKNOWN_FUNCTION_SILENT:
                self.error(t, ErrorCode.UNKNOWN_FUNCTION, function, via_fixed=via_fixed)
            return
        if function in _MCA_FROM_HOST:
            if self.application is not None:
                self.application.on_frame(function, Address(IdType(id_type), number), data, t)
            elif not broadcast:
                self.error(t, ErrorCode.NOT_RUNNING, function, via_fixed=via_fixed)
            return
        try:
            _, msg = m.decode(arbitration_id, data, sender=Direction.HOST_TO_BOARD)
        except FrameError as err:
            if broadcast and function == _PROGRAM:
                return
            code = ErrorCode.BAD_LENGTH if "length" in err.field else ErrorCode.BAD_VALUE
            self.error(t, code, function, via_fixed=via_fixed)
            return
        self._dispatch(msg, t, broadcast, via_fixed)

    def _dispatch(self, msg: m.BootMessage, t: float, broadcast: bool, via_fixed: bool) -> None:
        reply_t = t + self.timing.reply_us
        running = self.application is not None
        match msg:
            case m.Reset():
                self._reset(t, clear_autostart=False)
            case m.XReset():
                self._reset(t, clear_autostart=True)
            case m.InitRequest():
                self.bootloader.init(msg, t)
            case m.InfoRequest():
                self.bootloader.answer_info(reply_t, via_fixed)
            case m.ReportRequest():
                self.bootloader.report(msg, reply_t, via_fixed)
            case m.SetStatus():
                self.bootloader.set_status(msg, t, via_fixed)
            case m.Start():
                self._start_cmd(msg.target, t, via_fixed)
            case _ if msg.FUNCTION is Function.PROGRAM:
                if running:
                    if not broadcast:
                        self.error(t, ErrorCode.RUNNING, _PROGRAM, via_fixed=via_fixed)
                else:
                    self.programming.handle(msg, t, addressed=not broadcast,
                                            via_fixed=via_fixed)

    # ================================================================= memory, pins, LEDs
    def read_memory(self, space: Space, address: int, count: int) -> list[int] | None:
        """Words for a memory report: program or data flash, or X: external memory (with
        the FPGA registers at X:4000-403F); None if not readable."""
        if count == 0 or count > 0x100:
            return None
        if space is Space.X and address >= 0x2000 and address + count <= 0xFF80:
            return [self.xmem.read(a) for a in range(address, address + count)]
        mem = self.nv.space(space)
        if address < mem.base or address + count > mem.base + len(mem.words):
            return None
        return list(mem.read(address, count))

    def descriptor(self, target: Target) -> ImageDescriptor | None:
        """The image descriptor of the program in ``target`` (raises FrameError if corrupt)."""
        if target is Target.EXTRAM:
            if self.programming.extram is None:
                return None
            memory = self.programming.extram.memory[Space.P]
        elif self.nv.record.flash_valid:
            memory = self.nv.p
        else:
            return None
        return ImageDescriptor.from_words(list(memory.read(DESCRIPTOR_ADDRESS, DESCRIPTOR_WORDS)))

    def pins(self) -> dict[str, bool]:
        pos = self.identity.position
        return {
            "in_driven": self.powered and self.in_drive,
            "in_set": self.powered and self.bus.init_in_set(pos),
            "out_driven": self.powered and self.out_drive,
            "out_set": self.powered and self.bus.init_out_set(pos),
        }

    def leds(self) -> dict[str, str]:
        """LEDs as B.2.3 describes: init pins in the bootloader, program status when running."""
        if not self._powered:
            return {"red": "off", "yellow": "off", "green": "off"}
        if self.bus_off:  # the CAN controller is off the bus: the red LED says so
            shown = self._shown_leds()
            shown["red"] = "on"
            return shown
        return self._shown_leds()

    def _shown_leds(self) -> dict[str, str]:
        if self.application is not None:
            return self.application.leds(self.bus.now)
        pins = self.pins()
        on = {True: "on", False: "off"}
        return {"red": on[pins["in_driven"]], "yellow": on[pins["out_driven"]],
                "green": on[pins["in_set"]]}

    # ================================================================= start
    def _start_cmd(self, target: Target, t: float, via_fixed: bool) -> None:
        if self.application is not None and self.application.target is target:
            self.send(t + self.timing.reply_us, m.Ready(ReadyReason.STARTED, self.state, target),
                      via_fixed=via_fixed)
            return
        if self.application is not None or self.programming.busy:
            self.error(t, ErrorCode.RUNNING if self.application else ErrorCode.BUSY,
                       Function.START, target, via_fixed)
            return
        valid = (self.nv.record.flash_valid if target is Target.FLASH
                 else self.programming.extram is not None)
        if not valid:
            self.error(t, ErrorCode.NO_PROGRAM, Function.START, target, via_fixed)
            return
        self._start_program(target, t + self.timing.reply_us, announce=True, via_fixed=via_fixed)

    def _start_program(self, target: Target, t: float, *, announce: bool,
                       via_fixed: bool = False) -> None:
        self.bootloader.chain_active = False
        self.in_drive = self.out_drive = False
        self.programming.enabled = False
        if target is Target.FLASH:
            rec = self.nv.record
            name, progid = rec.name, rec.progid
        else:
            ext = self.programming.extram
            assert ext is not None
            name, progid = ext.name, ext.progid
        self.application = DspProgram(self, target, name, progid, defect=self.defect)
        if announce:
            self.send(t, m.Ready(ReadyReason.STARTED, self.state, target), via_fixed=via_fixed)
        self.application.start(t)

    # ================================================================= persistence
    def persist(self, record_only: bool = False) -> None:
        """Write non-volatile state to the fleet's state directory (if it has one)."""
        if self.state_file is None:
            return
        if record_only:
            self.nv.save_record(self.state_file)
        else:
            self.nv.save(self.state_file)
