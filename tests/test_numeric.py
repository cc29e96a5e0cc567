"""ucom_tools.virtual.hardware.numeric: the models' compiled stand-ins for builtins give the
builtin's value for every float (the fidelity of the fleet depends on it)."""

from __future__ import annotations

import math
import random
import struct

import pytest

from ucom_tools.virtual.hardware.numeric import round_half_even

EDGES = [0.0, -0.0, 0.5, -0.5, 1.5, -1.5, 2.5, -2.5, 3.5, 0.49999999999999994,
         -0.49999999999999994, 0.5000000000000001, -0.5000000000000001, 1e-300, -1e-300,
         5e-324, 0.9999999999999999, -0.9999999999999999, 2.0 ** 52 - 0.5, 2.0 ** 52 + 1,
         -(2.0 ** 52) + 0.5, 2.0 ** 53 - 1, 2.0 ** 53, 2.0 ** 63, -(2.0 ** 63), 1e300,
         -1e300, 4095.5, 3300.5, 32767.5, -32768.5, 65535.49999999999]


@pytest.mark.parametrize("x", EDGES)
def test_the_edges_round_as_round_does(x: float) -> None:
    assert round_half_even(x) == round(x)
    assert type(round_half_even(x)) is int


def test_random_floats_of_every_magnitude_round_as_round_does() -> None:
    rng = random.Random(17)
    checked = 0
    while checked < 200_000:
        bits = rng.getrandbits(64)
        x = struct.unpack("<d", struct.pack("<Q", bits))[0]
        if math.isnan(x) or math.isinf(x):
            continue
        assert round_half_even(x) == round(x), x
        checked += 1
    for _ in range(200_000):  # where the models round: small values, many near a tie
        x = rng.uniform(-70_000.0, 70_000.0)
        for y in (x, math.floor(x) + 0.5, math.nextafter(math.floor(x) + 0.5, math.inf),
                  math.nextafter(math.floor(x) + 0.5, -math.inf)):
            assert round_half_even(y) == round(y), y


@pytest.mark.parametrize(("x", "error"), [(math.nan, ValueError), (math.inf, OverflowError),
                                          (-math.inf, OverflowError)])
def test_what_cannot_be_rounded_raises_what_round_raises(x: float, error: type) -> None:
    with pytest.raises(error):
        round(x)
    with pytest.raises(error):
        round_half_even(x)
