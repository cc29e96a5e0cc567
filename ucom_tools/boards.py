"""Plug-on boards ("Ansteckboards") a UCoM is combined with (dissertation B.4, Tab. 4.3).

``UCoM@<board>`` when plugged on, ``UCoM-<board>`` when both share one PCB.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PlugOnBoard:
    key: str
    name: str
    carries: str


PLUG_ON_BOARDS: dict[str, PlugOnBoard] = {b.key: b for b in (
    PlugOnBoard("3M", "UCoM@3M (three-motor board)",
                "3 brushed motors 24 V / 5 A, 6 quadrature encoder inputs, current sensing, "
                "2 analog in, SPI, 3 I/O"),
    PlugOnBoard("UCoM-3M", "UCoM-3M (UCoM and three-motor board on one PCB)",
                "as the three-motor board; forearm of ARMAR-III"),
    PlugOnBoard("Valve", "UCoM@Ventiltreiberboard (valve driver)", "valve drivers"),
    PlugOnBoard("Sensor", "UCoM@Sensorboard", "sensor inputs"),
    PlugOnBoard("HighCurrent", "UCoM@Hochstromboard (high-current motor driver)",
                "motor driver up to 30 A"),
    PlugOnBoard("Test", "UCoM@Testboard", "test I/O"),
    PlugOnBoard("KairoAlpha", "UCoM-KairoAlpha (KAIRO-II Alpha module)", "2 motor stages"),
    PlugOnBoard("KairoGamma", "UCoM-KairoGamma (KAIRO-II Gamma module)", "3 motor stages"),
)}
