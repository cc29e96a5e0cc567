"""A stop signal held off by ``deferred`` is raised when the block ends, also when the
block ends by an error that a caller would take (and retry): the stop is never lost."""

from __future__ import annotations

import os
import signal

import pytest

from ucom_tools.signals import Terminated, deferred, stop_signals


def test_a_signal_inside_the_block_comes_at_its_end() -> None:
    with stop_signals(), pytest.raises(Terminated), deferred:
        os.kill(os.getpid(), signal.SIGTERM)
        reached_the_end = True
    assert reached_the_end


def test_a_signal_is_not_lost_when_the_block_ends_by_an_error() -> None:
    with stop_signals(), pytest.raises(Terminated) as got:
        try:
            with deferred:
                os.kill(os.getpid(), signal.SIGTERM)
                raise OSError("transmit queue full")  # what a sender offers again
        except OSError:
            pytest.fail("the error was raised instead of the stop")
    assert isinstance(got.value.__context__, OSError)


def test_a_ctrl_c_in_the_block_stays_one_ctrl_c() -> None:
    with stop_signals(), pytest.raises(KeyboardInterrupt) as got, deferred:
        os.kill(os.getpid(), signal.SIGINT)
        raise KeyboardInterrupt
    assert got.value.__context__ is None
