"""The trace tools, a layer of their own: decoding a trace into its conversation
(:mod:`.decode`, split by job: :mod:`.bus` the requests and deadlines, :mod:`.boot` the
bootloader's dialogue, :mod:`.program` the programming transfer, :mod:`.runtime` the run
time, :mod:`.conversation` the result, :mod:`.text` how values read), the CAN logs other
tools read (:mod:`.logs`: formats, the channel rule, reading, the ``--log`` writer) and
the run's recording (:mod:`.record`: ``--record`` and its values file), and the DBC
export (:mod:`.dbc`: what a stateless decoder can tell apart, and nothing else).  Nothing here
talks to boards; ``ucom_tools.ops`` does, and records through these."""
