"""The armar3 program's quiet check compares an axis's state before and after a cycle
(``Axis.state``): every field of ``_STATE`` must take part, by its exact value (a
float by its bits), and the two clocks left out must not."""

from __future__ import annotations

import pytest

from ucom_tools.virtual.programs import armar3_axis
from ucom_tools.virtual.programs.armar3_axis import _STATE, Axis

_OPTIONAL_FLOATS = {"pos_previous", "vel_previous"}


def _other(name: str, value: object) -> object:
    """A different value of the field's type."""
    if value is None:
        return 0.0 if name in _OPTIONAL_FLOATS else 0
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    assert isinstance(value, float), (name, value)
    return value + 1.5


def test_the_state_lists_every_field_but_the_two_clocks_and_the_slot_tables() -> None:
    assert set(_STATE) == set(armar3_axis._AXIS_SLOTS) - {
        "since_us", "settled_us", "so_slots", "ci_slots"}


@pytest.mark.parametrize("name", _STATE)
def test_a_change_of_any_compared_field_changes_the_state(name: str) -> None:
    axis = Axis(1)
    before = axis.state()
    setattr(axis, name, _other(name, getattr(axis, name)))
    assert axis.state() != before
    assert Axis(1).state() == before  # the same fields, the same state


@pytest.mark.parametrize("name", sorted(
    n for n in _STATE if isinstance(getattr(Axis(0), n), float) or n in _OPTIONAL_FLOATS))
def test_a_float_is_compared_by_its_bits(name: str) -> None:
    axis = Axis(0)
    setattr(axis, name, 0.0)
    zero = axis.state()
    setattr(axis, name, -0.0)
    assert axis.state() != zero  # equal by ==, not the same number to a later cycle
    if name in _OPTIONAL_FLOATS:
        setattr(axis, name, None)
        assert axis.state() != zero  # None is not 0.0


def test_the_clocks_left_out_do_not_change_the_state() -> None:
    axis = Axis(2)
    before = axis.state()
    axis.since_us += 250.0
    axis.settled_us += 250.0
    assert axis.state() == before
