"""How decoded values read: JSON-safe fields, candump-style frames, ranges, times, and
the texts of Program meta data, Ready messages and Info records."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import fields, is_dataclass
from datetime import datetime
from decimal import Decimal
from enum import Enum
from typing import Any

import can

from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    MetaField,
    ReadyReason,
    StatusOp,
    Target,
)
from ucom_tools.wire.info import BoardInfo
from ucom_tools.wire.transfer import decode_date


# ============================================================================ helpers
def jsonable(value: Any) -> Any:
    """``value`` as JSON: enums by name, bytes as hex, datetimes ISO, dataclasses as
    objects, Decimals as exact text."""
    if isinstance(value, Enum):
        return value.name
    if isinstance(value, bytes | bytearray):
        return bytes(value).hex(" ").upper()
    if isinstance(value, datetime):
        return value.isoformat()
    if isinstance(value, Decimal):
        return format(value, "f")
    if isinstance(value, bool | int | float | str) or value is None:
        return value
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [jsonable(v) for v in value]
    return str(value)


def raw_text(msg: can.Message) -> str:
    """``ID#DATA`` as candump prints it (``R`` for a remote frame)."""
    ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    if msg.is_remote_frame:
        return f"{ident}#R"
    return f"{ident}#{bytes(msg.data).hex().upper()}"


def _ranges(numbers: Iterable[int]) -> str:
    """1, 2, 3, 5 -> '1-3, 5'."""
    out: list[str] = []
    nums = sorted(set(numbers))
    i = 0
    while i < len(nums):
        j = i
        while j + 1 < len(nums) and nums[j + 1] == nums[j] + 1:
            j += 1
        out.append(str(nums[i]) if i == j else f"{nums[i]}-{nums[j]}")
        i = j + 1
    return ", ".join(out)


def _to(board: str) -> str:
    return " to every board" if board == "all" else f" to board {board}"


def _ms(seconds: float) -> str:
    return f"{seconds * 1000:.3f} ms"


def _meta_text(msg: m.ProgramMeta) -> str:
    if msg.field == MetaField.PROGID:
        return f"ProgID 0x{int.from_bytes(msg.value, 'big'):08X}"
    if msg.field == MetaField.SIZE:
        return f"size {int.from_bytes(msg.value, 'big')} words"
    if msg.field == MetaField.DATE:
        value = int.from_bytes(msg.value, "big")
        return f"date {decode_date(value).isoformat()}"
    text = msg.value.rstrip(b"\0").decode("latin-1")
    first = 4 * (msg.field - MetaField.NAME_0)
    return f"name[{first}:{first + 4}] {text!r}"


def _meta_fields(meta: dict[int, bytes]) -> dict[str, Any]:
    """What the META frames so far say: ProgID, size, date, name."""
    out: dict[str, Any] = {}
    if MetaField.PROGID in meta:
        out["progid"] = f"0x{int.from_bytes(meta[MetaField.PROGID], 'big'):08X}"
    if MetaField.SIZE in meta:
        out["size_words"] = int.from_bytes(meta[MetaField.SIZE], "big")
    if MetaField.DATE in meta:
        out["date"] = decode_date(int.from_bytes(meta[MetaField.DATE], "big")).isoformat()
    parts = [meta.get(MetaField.NAME_0 + i) for i in range(7)]
    if any(p is not None for p in parts):
        out["name"] = b"".join(p or b"" for p in parts).rstrip(b"\0").decode("latin-1")
    return out


def _ready_text(r: m.Ready) -> str:
    text = f"{r.reason.name} ({r.state.name})"
    if r.reason is ReadyReason.BOOT:
        text += f", serial 0x{r.value32:08X}"
    elif r.reason is ReadyReason.ERASED:
        text += f": receive ring {r.value16} frames, {r.value32} us per data frame"
    elif r.reason in (ReadyReason.PAUSE, ReadyReason.RESUME):
        text += f": {r.value16} frames buffered"
    elif r.reason is ReadyReason.STARTED:
        try:
            text += f": {Target(r.value16).name.lower()}"
        except ValueError:
            text += f": target {r.value16}"
    elif r.reason is ReadyReason.STATUS:
        try:
            op = StatusOp(r.value16 >> 8).name
        except ValueError:
            op = str(r.value16 >> 8)
        text += f": {op} {r.value16 & 0xFF}"
    return text


def _info_fields(info: BoardInfo) -> dict[str, Any]:
    fpga = info.fpga
    return {
        "state": info.state, "autostart": info.autostart, "prog_enable": info.prog_enable,
        "flash_valid": info.flash_valid, "extram_valid": info.extram_valid,
        "seq_id": info.seq_id, "fixed_id": info.fixed_id,
        "bootloader": f"{info.bootloader_version[0]}.{info.bootloader_version[1]}",
        "progid": f"0x{info.progid:08X}", "size_words": info.size_words,
        "programmed": info.programmed, "serial": f"0x{info.serial:08X}",
        "entry": f"P:{info.entry:04X}", "target": info.target, "name": info.name,
        "fpga": None if fpga is None else {"board_id": fpga.board_id, "app_id": fpga.app_id,
                                           "version": fpga.version},
        "measured_board_id": info.measured_board_id, "fpga_neutral": info.fpga_neutral,
        "descriptor": None if info.descriptor is None else {
            "board_id": info.descriptor.board_id, "app_id": info.descriptor.app_id,
            "fpga": f"{info.descriptor.fpga_major}.{info.descriptor.fpga_minor}",
            "version": f"{info.descriptor.version[0]}.{info.descriptor.version[1]}"},
        "descriptor_corrupt": info.descriptor_corrupt,
    }


def _info_text(info: BoardInfo) -> str:
    flags = [name for on, name in ((info.autostart, "AutoStart"),
                                   (info.prog_enable, "ProgEnable"),
                                   (info.flash_valid, "flash valid"),
                                   (info.extram_valid, "ExtRAM loaded")) if on]
    program = (f"'{info.name}' ProgID 0x{info.progid:08X}, {info.size_words} words"
               if info.name or info.progid else "no program")
    fpga = info.fpga
    parts = [f"{info.state.name}", program, f"serial 0x{info.serial:08X}",
             f"seq ID {info.seq_id or '-'}, fixed ID {info.fixed_id or '-'}",
             "flags " + (", ".join(flags) if flags else "none"),
             "FPGA " + (f"Board-ID {fpga.board_id} App-ID {fpga.app_id} v{fpga.version}"
                        if fpga else "unreadable")
             + f", plug-on Board-ID {info.measured_board_id}"
             + (" (NEUTRAL)" if info.fpga_neutral else "")]
    if info.programmed is not None:
        parts.append(f"programmed {info.programmed.isoformat()}")
    return "; ".join(parts)


