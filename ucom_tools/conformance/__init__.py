"""The protocol conformance suite (``ucom conformance``): cases that check, over the bus,
that boards speak the protocol as ``man/ucom-protocol.7`` specifies it - content and
timing - grouped as the page is, each citing the section it checks.

:mod:`.case` defines a case and its failure; :mod:`.bench` is what a case works with
(one bus, its clients, the frames of the case, timed requests); :mod:`.runner` runs a
selection on every bus, resets the boards between cases and leaves them as found;
:mod:`.junit` writes the report; the cases live in the ``cases_*`` modules.
"""
