"""The protocol conformance suite (``ucom conformance``): cases that check, over the bus,
that boards speak the protocol as ``man/ucom-protocol.7`` specifies it - content and
timing - grouped as the page is, each citing the section it checks.

:mod:`.case` defines a case, :mod:`.outcome` how one fails or is skipped; :mod:`.bench`
is what a case works with (one bus, its clients, the frames of the case, timed
requests); the cases live in the ``cases_*`` modules, :mod:`.catalogue` lists them all;
:mod:`.runner` runs a selection on every bus and resets the boards between cases;
:mod:`.restore` notes the boards as found and leaves them so whatever ends the suite,
:mod:`.shield` keeps a signal from cutting that short; :mod:`.junit` writes the report.
"""
