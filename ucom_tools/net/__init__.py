"""The run time on the robot's network (the mcabrowser of ucom-tools), on Eclipse Zenoh.

A running :class:`~ucom_tools.ops.remote.RemotePart` is *shared* (:mod:`.share`): its
structure, its values batched per board and period, per-edge values while someone
subscribes, its events and liveliness, and (only where allowed) writes and a stop from
other hosts.  :mod:`.client` is the other side (``ucom browse``).  The key expressions and
payloads are specified in ``man/ucom-network.7`` and built in :mod:`.keys`; the sessions
(peer mode, explicit endpoints, no multicast scouting) in :mod:`.session`.

Nothing here is a network layer of our own: Zenoh carries everything.
"""
