"""``ucom dbc`` against cantools on recorded traces: no frame labelled wrongly.

The product records an init, a flash and 2 s of run time of the virtual ARMAR-III; each
frame is decoded by cantools with the exported database (the Python API, strictly and
with truncated frames allowed, and the ``cantools decode`` command line on a
candump-style text) and compared with ``ucom decode``'s stateful reading of the same
frame (:func:`ucom_tools.trace.decode.decode_frames`, each message's ``members``): a frame
cantools decodes must be the function, board (or map, or data-frame slot) and op / kind /
reason ucom reads there, with the same value in every field both name.  A frame cantools
cannot decode is allowed (the database describes only what a stateless decoder can tell
apart); the shares are printed.
"""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from click.testing import CliRunner

from ucom_tools.cli.main import cli
from ucom_tools.trace import dbc as dbc_ops
from ucom_tools.trace.decode import Message, decode_frames, read_trace
from ucom_tools.wire.ids import Function

cantools = pytest.importorskip("cantools")

ROOT = Path(__file__).resolve().parents[1]
IMAGE = ROOT / "firmware_images" / "armar3.fl.S"


# ============================================================================ traces
@pytest.fixture(scope="module")
def traces(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """init, flash and run, recorded by ucom itself (the flash into a --state directory
    that the run then starts)."""
    d = tmp_path_factory.mktemp("interop")
    state = d / "S"
    runs = {
        "init": ["init", "--virtual", "armar3", "--log", str(d / "init.asc")],
        "flash": ["flash", str(IMAGE), "--virtual", "armar3", "--state", str(state),
                  "--log", str(d / "flash.asc")],
        "run": ["remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
                "--for", "2", "--record", str(d / "run.blf")],
    }
    for args in runs.values():
        r = CliRunner().invoke(cli, args)
        assert r.exit_code == 0, (args, r.stderr)
    return {"init": d / "init.asc", "flash": d / "flash.asc", "run": d / "run.blf"}


@pytest.fixture(scope="module")
def dbc_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("dbc") / "ucom.dbc"
    r = CliRunner().invoke(cli, ["dbc", "-o", str(path)])
    assert r.exit_code == 0, r.stderr
    return path


@pytest.fixture(scope="module")
def db(dbc_file: Path) -> Any:
    return cantools.database.load_file(str(dbc_file), strict=True)


# ============================================================================ ucom's reading
@dataclass(frozen=True)
class Reading:
    """What ucom decode makes of one frame."""

    function: str
    board: str
    fields: Mapping[str, Any]
    data_frame: bool
    """A Program data frame (a frame of a BLOCK message other than the BLOCK itself)."""


def readings(frames: list[can.Message]) -> dict[int, Reading]:
    """Every frame's reading, by its position in the trace: each message of the
    conversation stands for the frames its ``members`` name."""
    out: dict[int, Reading] = {}
    for msg in decode_frames(frames).messages():
        for pos in msg.members:
            assert pos not in out, f"frame {pos} in two messages"
            out[pos] = _reading(msg, pos)
    return out


def _reading(msg: Message, pos: int) -> Reading:
    data = msg.function == "Program" and (msg.fields.get("op") == "DATA"
                                          or pos != msg.index)
    return Reading(msg.function, msg.board, msg.fields, data)


# ============================================================================ comparison
def _hex(text: str) -> int:
    return int(text.split(":")[-1], 16)


def _value(decoded: Any) -> tuple[str | None, float]:
    """A cantools value as (choice name or None, number); the command line's text too."""
    if isinstance(decoded, str):
        try:
            return None, float(decoded)
        except ValueError:
            return decoded, float("nan")
    name = getattr(decoded, "name", None)
    return name, float(getattr(decoded, "value", decoded))


def same(decoded: Any, ucom: Any) -> bool:
    """A cantools value and ucom's (enum names, bools, 0x.. and P:.. texts, numbers)."""
    name, number = _value(decoded)
    if isinstance(ucom, bool):
        return number == int(ucom)
    if isinstance(ucom, str) and re.fullmatch(r"(0x|[PX]:)[0-9A-Fa-f]+", ucom):
        return number == _hex(ucom)
    if isinstance(ucom, str):
        return name == ucom
    return number == ucom


def _edges(sig: Mapping[str, Any], prefix: str) -> list[int]:
    return [int(_value(sig[f"{prefix}{i}"])[1]) for i in range(4) if f"{prefix}{i}" in sig]


Check = Callable[[Mapping[str, Any], Reading], list[str]]


def _fields(pairs: Mapping[str, str]) -> Check:
    """Signal -> ucom field: equal where both are there."""
    def check(sig: Mapping[str, Any], r: Reading) -> list[str]:
        return [f"{s}={sig[s]!r} but ucom {f}={r.fields[f]!r}" for s, f in pairs.items()
                if s in sig and f in r.fields and not same(sig[s], r.fields[f])]
    return check


def _values(first: int) -> Check:
    """MCA Controller Input / Parameter / DSP CI: the index and the raw value bytes."""
    def check(sig: Mapping[str, Any], r: Reading) -> list[str]:
        bad = _fields({"FirstIndex": "index", "Kind": "kind"})(sig, r)
        data = bytes.fromhex(r.fields["data"]) if "data" in r.fields else b""
        for i, byte in enumerate(data):
            s = f"Data{first + i}"
            if s in sig and not same(sig[s], byte):
                bad.append(f"{s}={sig[s]!r} but ucom data byte {byte}")
        for i, value in enumerate(r.fields.get("values", [])):  # a signal per value
            s = f"Value{i}"
            if s in sig and not same(sig[s], value["raw"]):
                bad.append(f"{s}={sig[s]!r} but ucom's value {i} is {value['raw']} "
                           f"({value['name']})")
        return bad
    return check


def _admin(sig: Mapping[str, Any], r: Reading) -> list[str]:
    bad = _fields({"Op": "op", "Alive_TimeoutMs": "watchdog_ms", "SoMap_Map": "map",
                   "SoMap_Period": "period", "CiMap_Map": "map"})(sig, r)
    so = [e for e in _edges(sig, "SoMap_Edge") if e != 0xFF]
    if "SoMap_Edge3" in sig and so != r.fields.get("edges"):
        bad.append(f"SO map edges {so} but ucom {r.fields.get('edges')}")
    ci = _edges(sig, "CiMap_Slot")
    if len(ci) == 4 and ci != r.fields.get("slots"):
        bad.append(f"CI map slots {ci} but ucom {r.fields.get('slots')}")
    return bad


CHECKS: dict[Function, Check] = {
    Function.SET_STATUS: _fields({"Op": "op", "Value": "value"}),
    Function.INIT_REQUEST: _fields({"Op": "op", "Number": "number"}),
    Function.START: _fields({"Target": "target"}),
    Function.INIT_ACK: _fields({"Kind": "kind", "SeqID": "seq_id", "FixedID": "fixed_id",
                                "Serial": "serial"}),
    Function.INFO: _fields({"State": "state", "AutoStart": "autostart",
                            "ProgEnable": "prog_enable", "FlashValid": "flash_valid",
                            "ExtRamLoaded": "extram_valid", "SeqID": "seq_id",
                            "FixedID": "fixed_id", "ProgID": "progid",
                            "SizeWords": "size_words", "Serial": "serial", "Entry": "entry",
                            "Target": "target"}),
    Function.READY: _fields({"Reason": "reason", "State": "state"}),
    Function.PROGRAM_FINISHED: _fields({"Kind": "kind", "Result_Status": "status",
                                        "Result_Reports": "reports",
                                        "Result_ProgID": "progid"}),
    Function.MCA_READY: _fields({"State": "state", "Answers": "answers", "CountCI": "ci",
                                 "CountSO": "so", "CountPAR": "par"}),
    Function.MCA_START: _fields({"Op": "op"}),
    Function.MCA_DUMPIO_DESCR: _fields({"Kind": "kind", "Index": "index"}),
    Function.MCA_DUMPIO_DESCR_REQUEST: _fields({"Kind": "kind", "Index": "index"}),
    Function.MCA_CONTROLLER_INPUT: _values(1),
    Function.MCA_PARAMETER: _values(1),
    Function.MCA_DSP_CI: _values(2),
    Function.MCA_ADMIN_DATA: _admin,
}
"""Per function, the fields cantools and ucom both name."""

ENTRIES = {e.frame_id: e for e in dbc_ops.entries()}


def _board_of(entry: dbc_ops.Entry) -> str:
    """ucom's board label for the DBC message's identifier (its name's suffix)."""
    suffix = entry.name.rsplit("_", 1)[1]
    if entry.layout in dbc_ops.PROCESS_DATA:
        return f"{'SO' if entry.layout.stem == 'SoMap' else 'CI'} map {suffix}"
    return {"All": "all", "Unnumbered": "unnumbered"}.get(suffix, suffix)


def disagreements(frame_id: int, name: str, sig: Mapping[str, Any], r: Reading) -> list[str]:
    """How cantools' decoding (message ``name``, signals ``sig``) of a frame differs
    from ucom's reading of it; empty when they agree."""
    entry = ENTRIES[frame_id]
    assert entry.name == name
    fn = entry.layout.function
    if fn.label != r.function:
        return [f"{name} but ucom reads {r.function}"]
    if fn is Function.PROGRAM:  # a data frame (any first byte) or a control frame (op)
        claims = set(sig) - {"Words"}
        if r.data_frame and claims:
            return [f"{name} with {sorted(claims)}, but ucom reads a data frame"]
        if not r.data_frame and "Words" in sig:
            return [f"{name} as a data frame, but ucom reads a {r.fields.get('op')} frame"]
        return _fields({"Op": "op"})(sig, r)
    bad = [] if _board_of(entry) == r.board else [f"{name} but ucom's board {r.board}"]
    check = CHECKS.get(fn)
    return bad + (check(sig, r) if check is not None else [])


# ============================================================================ decoding
@dataclass
class Tally:
    frames: int = 0
    decoded: int = 0
    differ: int = 0

    def share(self) -> str:
        return f"{self.decoded}/{self.frames} decoded ({100 * self.decoded / self.frames:.1f} %)"


def api_tally(db: Any, frames: list[can.Message], reading: dict[int, Reading], *,
              truncated: bool, problems: list[str]) -> Tally:
    t = Tally(len(frames))
    for pos, f in enumerate(frames):
        try:
            sig = db.decode_message(f.arbitration_id, bytes(f.data),
                                    allow_truncated=truncated)
        except (KeyError, cantools.database.DecodeError):
            continue
        t.decoded += 1
        name = db.get_message_by_frame_id(f.arbitration_id).name
        bad = disagreements(f.arbitration_id, name, sig, reading[pos])
        if bad:
            t.differ += 1
            problems.append(f"frame {pos} {f.arbitration_id:03X}#{bytes(f.data).hex()}: "
                            + "; ".join(bad))
    return t


LINE = re.compile(r"^\(\d+\.\d+\) can0 ([0-9A-F]{3})#([0-9A-F]*) :: (\w+)\((.*)\)$")


def _choice(message: Any, signal: str, text: str) -> Any:
    """A value of the command line's output: a choice's name as the choice (its name
    and number), a number without its unit, other text as it stands."""
    sig = message.get_signal_by_name(signal)
    if sig.unit and text.endswith(f" {sig.unit}"):
        text = text[:-len(sig.unit) - 1]
    return next((c for c in (sig.choices or {}).values() if str(c) == text), text)


def cli_tally(db: Any, dbc_file: Path, frames: list[can.Message],
              reading: dict[int, Reading], problems: list[str]) -> Tally:
    """``cantools decode`` (strict, its default) on the frames as candump -L lines."""
    text = "".join(f"({pos}.0) can0 {f.arbitration_id:03X}#{bytes(f.data).hex().upper()}\n"
                   for pos, f in enumerate(frames))
    out = subprocess.run([sys.executable, "-m", "cantools", "decode", "--single-line",
                          str(dbc_file)], input=text, capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert len(out) == len(frames)
    t = Tally(len(frames))
    for pos, line in enumerate(out):
        match = LINE.match(line)
        if match is None:
            assert " :: " in line, line
            continue
        frame_id, _, name, body = match.groups()
        texts = dict(item.split(": ", 1) for item in body.split(", ")) if body else {}
        sig = {s: _choice(db.get_message_by_name(name), s, text) for s, text in texts.items()}
        t.decoded += 1
        bad = disagreements(int(frame_id, 16), name, sig, reading[pos])
        if bad:
            t.differ += 1
            problems.append(f"cantools decode, frame {pos}: " + "; ".join(bad))
    return t


@pytest.mark.parametrize("trace", ["init", "flash", "run"])
def test_no_frame_labelled_differently(traces: dict[str, Path], db: Any, dbc_file: Path,
                                       trace: str) -> None:
    frames = read_trace(traces[trace])
    reading = readings(frames)
    assert sorted(reading) == list(range(len(frames)))  # ucom reads every frame
    problems: list[str] = []
    strict = api_tally(db, frames, reading, truncated=False, problems=problems)
    loose = api_tally(db, frames, reading, truncated=True, problems=problems)
    command = cli_tally(db, dbc_file, frames, reading, problems)
    print(f"\n{trace}: {len(frames)} frames; decode_message strict {strict.share()}, "
          f"allow_truncated {loose.share()}; cantools decode {command.share()}; "
          f"labelled differently {strict.differ} / {loose.differ} / {command.differ}")
    assert problems == [], "\n".join(problems[:20])
    assert strict.decoded > 0 and command.decoded > 0
    assert loose.decoded >= strict.decoded >= command.decoded
