"""Plug-on boards ("Ansteckboards") a UCoM is combined with (dissertation B.4, Tab. 4.3),
with the 4-bit Board-IDs their resistor networks give (ours to assign; B.3.2, Tab. B.5),
and the applications (App-IDs) known for them.

``UCoM@<board>`` when plugged on, ``UCoM-<board>`` when both share one PCB.  Board-ID 15
is what the FPGA reads with no plug-on board (all pull-ups); 0 is reserved.
"""

from __future__ import annotations

from dataclasses import dataclass

NO_BOARD_ID = 15


@dataclass(frozen=True)
class PlugOnBoard:
    key: str
    board_id: int
    name: str
    motors: int = 0
    encoders: int = 0
    valves: int = 0
    analog_in: int = 0
    digital_io: int = 0
    max_current_a: float = 0.0
    note: str = ""

    @property
    def carries(self) -> str:
        parts = []
        if self.motors:
            parts.append(f"{self.motors} motor stage(s) up to {self.max_current_a:g} A")
        if self.encoders:
            parts.append(f"{self.encoders} quadrature encoder inputs")
        if self.valves:
            parts.append(f"{self.valves} valve drivers")
        if self.analog_in:
            parts.append(f"{self.analog_in} analog inputs")
        if self.digital_io:
            parts.append(f"{self.digital_io} digital I/O")
        if self.note:
            parts.append(self.note)
        return ", ".join(parts)


PLUG_ON_BOARDS: dict[str, PlugOnBoard] = {b.key: b for b in (
    PlugOnBoard("3M", 1, "UCoM@3M (three-motor board)", motors=3, encoders=6, analog_in=2,
                digital_io=3, max_current_a=5, note="current sensing, SPI; 24 V"),
    PlugOnBoard("UCoM-3M", 2, "UCoM-3M (UCoM and three-motor board on one PCB)", motors=3,
                encoders=6, analog_in=2, digital_io=3, max_current_a=5,
                note="forearm of ARMAR-III"),
    PlugOnBoard("Valve", 3, "UCoM@Ventiltreiberboard (valve driver)", valves=8,
                digital_io=4),
    PlugOnBoard("Sensor", 4, "UCoM@Sensorboard", analog_in=8, digital_io=8,
                note="SSI and SPI sensor inputs"),
    PlugOnBoard("HighCurrent", 5, "UCoM@Hochstromboard (high-current motor driver)",
                motors=1, encoders=2, analog_in=2, max_current_a=30),
    PlugOnBoard("Test", 6, "UCoM@Testboard", analog_in=8, digital_io=16,
                note="LEDs and switches for every FPGA pin"),
    PlugOnBoard("KairoAlpha", 7, "UCoM-KairoAlpha (KAIRO-II Alpha module)", motors=2,
                encoders=4, analog_in=2, max_current_a=5),
    PlugOnBoard("KairoGamma", 8, "UCoM-KairoGamma (KAIRO-II Gamma module)", motors=3,
                encoders=6, analog_in=3, max_current_a=5),
)}

BY_ID: dict[int, PlugOnBoard] = {b.board_id: b for b in PLUG_ON_BOARDS.values()}

APPLICATIONS: dict[tuple[int, int], str] = {
    (1, 1): "ARMAR-III cascaded velocity/position PID, 3 axes",
    (1, 2): "LAURON-IV leg controller",
    (1, 3): "RoSi scanner rotation",
    (1, 4): "Puma200 joint controller",
    (2, 1): "ARMAR-III forearm (UCoM-3M)",
    (3, 1): "valve control",
    (4, 1): "sensor acquisition",
    (5, 1): "high-current drive",
    (6, 1): "board test",
    (7, 1): "KAIRO-II segment drive",
    (8, 1): "KAIRO-II joint element",
}


def board_name(board_id: int) -> str:
    """A Board-ID as a name (``3M``), or ``none``/``#n`` when unknown."""
    if board_id == NO_BOARD_ID:
        return "none"
    b = BY_ID.get(board_id)
    return b.key if b else f"#{board_id}"


def app_name(board_id: int, app_id: int) -> str:
    return APPLICATIONS.get((board_id, app_id), f"App-ID {app_id}")
