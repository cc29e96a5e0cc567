"""Fixed, seeded scenarios of the virtual fleet and their traces, for the fidelity test.

The model's fidelity is the product: bit timing and stuff bits, arbitration, the boards'
answer times, erase and program times, the programs' control laws, the watchdog.  Each
scenario runs the real product code (ops, protocol clients, the in-process fleet in
virtual time) and a sniffer on every simulated bus records each frame that ended on it:
bus, virtual end time (exact, ``float.hex``), identifier and data.  The traces recorded
from the code as it was (``tests/data/golden/``, made by ``python tools/record_golden.py``)
must stay identical through every optimisation; ``tests/test_fidelity.py`` compares them.
"""

from __future__ import annotations

import gzip
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ucom_tools.image.formats import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashRequest
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.robot import ConnectSpec, Robot, open_robot

ROOT = Path(__file__).resolve().parent.parent
GOLDEN = ROOT / "tests" / "data" / "golden"
WHEN = datetime(2026, 12, 1, 12, 0, tzinfo=UTC)
"""The programming date of every scenario's transfers (else it is the wall clock's)."""

Frame = tuple[str, str, int, str]
"""(bus, virtual end time as float.hex, identifier, data as hex)."""


class Sniffer:
    """A node on one simulated bus that keeps every frame that ends on it."""

    def __init__(self, bus: str, frames: list[Frame]) -> None:
        self.bus = bus
        self.frames = frames

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float, *extra: Any) -> None:
        self.frames.append((self.bus, float(t_end).hex(), arbitration_id, bytes(data).hex()))

    def on_extended_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        self.on_frame(arbitration_id | 1 << 31, data, t_end)


@contextmanager
def sniffed(robot: Robot) -> Iterator[list[Frame]]:
    """Every frame on every bus of ``robot`` (an in-process virtual fleet) meanwhile."""
    frames: list[Frame] = []
    attached = []
    for name, handle in robot.buses.items():
        sim = handle.bus.sim  # type: ignore[attr-defined]
        node = Sniffer(name, frames)
        sim.attach(node)
        attached.append((sim, node))
    try:
        yield frames
    finally:
        for sim, node in attached:
            sim.detach(node)


def flash_armar3(state: Path) -> list[Frame]:
    """A whole-robot flash of ARMAR-III (init, ProgEnable, the broadcast transfer of
    armar3.fl.S, verify, AutoStart, start) into erased boards."""
    image = load_image(ROOT / "firmware_images" / "armar3.fl.S")
    robot = open_robot(ConnectSpec(virtual="armar3", state_dir=state))
    try:
        with sniffed(robot) as frames:
            result = flash(robot, FlashRequest(image, plan=image.plan(when=WHEN),
                                               autostart=True, start=True))
        assert result.all_verified and not result.failed, result
    finally:
        robot.close()
    return frames


def init_with_wiring_fault() -> list[Frame]:
    """The init chain of an arm whose init line is broken after its second board."""
    robot = open_robot(ConnectSpec(virtual=str(ROOT / "tests" / "data" /
                                               "arm_broken_line.toml")))
    try:
        with sniffed(robot) as frames:
            for handle in robot.buses.values():
                handle.client.init_chain()
    finally:
        robot.close()
    return frames


def run_armar3(state: Path, seconds: float = 2.0) -> list[Frame]:
    """``seconds`` of ARMAR-III's 1 kHz exchange with set-points (in boards flashed by
    :func:`flash_armar3`, which must have run on ``state``)."""
    with RemotePart.open("armar3", virtual=True, state_dir=state) as part, \
            sniffed(part.robot) as frames:
        part["Right Eye Target"] = 1000
        part["Left Eye Target"] = -1000
        part["Neck Yaw Target"] = -2000
        part["Right Elbow Target"] = 1500
        for _ in range(int(seconds * 1000)):
            part.cycle()
    return frames


def scenarios(state: Path) -> dict[str, Callable[[], list[Frame]]]:
    """The scenarios by name, in the order they must run (run needs flash's boards)."""
    return {"flash": lambda: flash_armar3(state),
            "init_fault": init_with_wiring_fault,
            "run": lambda: run_armar3(state)}


def dump(frames: list[Frame]) -> bytes:
    lines = (f"{bus} {t} {ident:03X} {data}\n" for bus, t, ident, data in frames)
    return gzip.compress("".join(lines).encode(), mtime=0)


def load(path: Path) -> list[Frame]:
    frames: list[Frame] = []
    for line in gzip.decompress(path.read_bytes()).decode().splitlines():
        bus, t, ident, *data = line.split(" ")
        frames.append((bus, t, int(ident, 16), data[0] if data else ""))
    return frames
