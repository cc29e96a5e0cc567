"""One robot, one loop: the Zenoh session a share opens, and the other loop of the same
robot it may find on the network (``man/ucom-network.7``).

A share listens on its endpoint; where the address is in use it asks who listens there.
A loop of the same robot (its liveliness token, its structure) makes it refuse, unless
``force``: then it joins that network as a peer instead of listening.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import zenoh

from ucom_tools.errors import BusError, BusTaken
from ucom_tools.net import keys
from ucom_tools.net.session import address_in_use, config, open_session

PROBE_S = 1.0
"""How long a new share looks for the robot's liveliness token elsewhere on the network."""


def open_listening(robot: str, endpoint: str | None, config_file: str | Path | None, *,
                   force: bool) -> tuple[zenoh.Session, str | None]:
    """The session of robot ``robot``'s share, listening on ``endpoint`` (or as
    ``config_file`` says), and the endpoint it joined instead (``force``, where another
    loop of the robot listens there; else None)."""
    listen = [endpoint] if endpoint is not None else None
    try:
        return open_session(config(listen=listen, file=config_file),
                            endpoint or str(config_file)), None
    except BusError as err:
        if endpoint is None or not address_in_use(err):
            raise
        other = _probe(robot, endpoint, config_file)
        if other is None:
            raise BusError(f"cannot listen on {endpoint}: the address is in use "
                           "(and no ucom robot of that name answers there)") from None
        if not force:
            raise BusTaken(refusal(robot, endpoint, other)) from None
        # forced: join that network as a peer
        return open_session(config(listen=[], connect=[endpoint], file=config_file,
                                   connect_timeout_s=PROBE_S), endpoint), endpoint


def _probe(robot: str, endpoint: str, config_file: str | Path | None
           ) -> dict[str, Any] | None:
    """The structure of this robot's loop that listens on ``endpoint``, if one does."""
    try:
        s = open_session(config(listen=[], connect=[endpoint], file=config_file,
                                connect_timeout_s=PROBE_S), endpoint)
    except BusError:
        return None
    try:
        return other_loop(s, robot)
    finally:
        s.close()


def other_loop(s: zenoh.Session, robot: str) -> dict[str, Any] | None:
    """Another loop of ``robot`` reachable from session ``s``: its structure (or an empty
    one where it does not answer), None where there is none."""
    if not s.info.peers_zid() and not s.info.routers_zid():
        return None
    deadline = time.monotonic() + PROBE_S
    found = False
    while not found and time.monotonic() < deadline:
        found = any(r.ok is not None for r in s.liveliness().get(
            keys.robot_key(robot, "alive"), timeout=PROBE_S))
        if not found:
            time.sleep(0.05)  # the peer's declarations may still be on their way
    if not found:
        return None
    for r in s.get(keys.robot_key(robot, "structure"), timeout=PROBE_S):
        if r.ok is not None:
            try:
                return keys.loads(r.ok.payload.to_bytes())
            except ValueError:
                pass
    return {}


def refusal(robot: str, endpoint: str | None, other: dict[str, Any]) -> str:
    """Why a share of ``robot`` is refused: ``other``, its loop, runs on the network."""
    who = ", ".join(f"{k} {other[k]}" for k in ("host", "pid", "listen") if other.get(k))
    since = other.get("started")
    when = f", since {time.strftime('%H:%M:%S', time.localtime(since))}" \
        if isinstance(since, int | float) else ""
    return (f"robot {robot!r} already runs its loop on this Zenoh network"
            f"{' (' + who + when + ')' if who or when else ''}, reached on "
            f"{endpoint or 'the configured endpoints'}: one robot, one loop; stop "
            "that one first")
