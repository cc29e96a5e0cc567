"""A late answer is not the next request's: an MCA Ready that came after its request's
wait ended (a slow network, a board that answered late) stays in the client's queue; the
next request of the same kind must not take it for its own answer (a second PC asking
the boards' run state saw RUNNING after the loop had stopped them)."""

from __future__ import annotations

from collections.abc import Callable

from ucom_tools.wire import mca
from ucom_tools.wire.ids import seq

from .test_mutants import Bench, bench  # noqa: F401


def test_a_query_takes_no_answer_that_came_before_it(bench: Callable[..., Bench],  # noqa: F811
                                                     ) -> None:
    b = bench(program=True)
    b.started()
    assert b.mca.start(seq(1)).state is mca.RunState.RUNNING
    b.mca._send(mca.McaStart(mca.StartOp.QUERY), seq(1))  # asked, its answer not awaited
    b.wait(0.005)  # the answer (RUNNING) is queued meanwhile
    b.link.send_raw(*mca.encode(mca.McaStart(mca.StartOp.STOP), seq(1)))  # another PC
    b.wait(0.005)
    assert b.mca.query(seq(1)).state is mca.RunState.STOPPED
