"""The run-time part of the PC (``dsp_remote_part``, dissertation 5.2.2):
:class:`RemotePart`, a robot's boards in the cyclic exchange, their edges under
robot-wide names (``from ucom_tools.ops.remote import RemotePart``, as the README shows).

The part is composed of parts that each do one job, a module each:

- :mod:`.part`: :class:`RemotePart`: opens, checks, starts and stops the boards;
- :mod:`.check`: the start-up check of the boards against their trees;
- :mod:`.values`: the values by name (what the PC holds, what the boards sent);
- :mod:`.loop`: the PC's loop, every period;
- :mod:`.watch`: which board is lost (the loop's watch over the SO maps);
- :mod:`.conversations`: what the loop steps after each cycle's drain: the rejoins
  (:mod:`.rejoin`) and the writes it does not wait for (:mod:`.par_write`);
- :mod:`.faults` and :mod:`.report`: what is reported (lost boards, events, figures);
- the loop's state for everyone else: :mod:`.publish` (the snapshots it hands over),
  :mod:`.image` (its structure as plain data), :mod:`.feed` and :mod:`.mirror` (the two
  ends of the pipes to the consumers' process), :mod:`.requests` (what the consumers
  ask of the loop, applied on its thread).
"""

from ucom_tools.ops.remote.part import RemotePart

__all__ = ["RemotePart"]
