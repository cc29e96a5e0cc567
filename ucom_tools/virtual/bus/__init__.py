"""The bus and its clock: a simulated CAN bus (:mod:`~ucom_tools.virtual.bus.simbus`:
arbitration, bit-exact timing, load counters, the init line), the fleet clock every bus
and board of a fleet is scheduled on (:mod:`~ucom_tools.virtual.bus.clock`), and frames
lost on purpose (:mod:`~ucom_tools.virtual.bus.loss`).  It knows nothing of boards but
what a node on the bus is."""
