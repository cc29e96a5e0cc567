"""``ucom fleet serve``: a virtual fleet served to other processes with the socketcand
protocol (raw mode).  :mod:`~ucom_tools.virtual.serve.socketcand` accepts the clients
(and says what no client can do to the others), :mod:`~ucom_tools.virtual.serve.connection`
serves one, :mod:`~ucom_tools.virtual.serve.outbox` queues what is written to it,
:mod:`~ucom_tools.virtual.serve.elements` answers what comes before raw mode;
:mod:`~ucom_tools.virtual.serve.multiserve` serves each bus from a process of its own
(:mod:`~ucom_tools.virtual.serve.multiserve_dispatch` hands the clients over,
:mod:`~ucom_tools.virtual.serve.multiserve_bus` is one bus's process)."""
