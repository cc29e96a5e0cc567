"""The model's fidelity, bit for bit: fixed scenarios (a whole-robot flash, an init with a
wiring fault, 2 s of the 1 kHz exchange with set-points) give exactly the frame sequences
recorded from the code before any optimisation (identifier, data, virtual end time, per
bus).  See ``tests/fidelity.py``; re-record only for an intended change of the model."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests import fidelity


def first_difference(got: list[fidelity.Frame], want: list[fidelity.Frame]) -> str:
    for bus in sorted({f[0] for f in want} | {f[0] for f in got}):
        g = [f for f in got if f[0] == bus]
        w = [f for f in want if f[0] == bus]
        for i, (a, b) in enumerate(zip(g, w, strict=False)):
            if a != b:
                return (f"{bus} frame {i}: got {a[2]:03X}#{a[3]} at {float.fromhex(a[1]):.3f} us,"
                        f" recorded {b[2]:03X}#{b[3]} at {float.fromhex(b[1]):.3f} us")
        if len(g) != len(w):
            return f"{bus}: {len(g)} frames, recorded {len(w)}"
    return "the buses' frames interleave differently"


@pytest.fixture(scope="module")
def traces(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[fidelity.Frame]]:
    state: Path = tmp_path_factory.mktemp("fidelity")
    return {name: scenario() for name, scenario in fidelity.scenarios(state).items()}


@pytest.mark.parametrize("name", ["flash", "init_fault", "run"])
def test_the_frames_are_those_recorded(traces: dict[str, list[fidelity.Frame]],
                                       name: str) -> None:
    want = fidelity.load(fidelity.GOLDEN / f"{name}.trace.gz")
    got = traces[name]
    assert want, "an empty golden trace proves nothing"
    assert got == want, first_difference(got, want)


def test_a_changed_frame_is_found() -> None:
    """The comparison itself can fail: one bit of one frame is enough."""
    want = fidelity.load(fidelity.GOLDEN / "init_fault.trace.gz")
    bus, t, ident, data = want[3]
    changed = [*want[:3], (bus, t, ident ^ 1, data), *want[4:]]
    assert changed != want
    assert "frame" in first_difference(changed, want)
