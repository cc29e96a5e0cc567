"""Zenoh sessions as ucom-tools opens them: peer mode, explicit endpoints, multicast
scouting off (``man/ucom-network.7``, SESSIONS).

A robot's share *listens* on its endpoint (default ``tcp/127.0.0.1:7447``: loopback only;
give an address of the robot's network to be reached from other hosts); a browser
*connects* to it.  A full Zenoh configuration file (JSON5: TLS, authentication, access
control, routers) may be given instead; its endpoints are replaced only by one given
explicitly, and multicast scouting is off whatever it says.
"""

from __future__ import annotations

import json
from pathlib import Path

import zenoh

from ucom_tools.errors import BusError, InputError
from ucom_tools.net.keys import DEFAULT_ENDPOINT

LEASE_S = 3.0
"""A session closes its link to a peer it has heard nothing from this long (Zenoh's
lease; its default is 10 s): a robot whose network went away is "connection lost" for
a browser within 3 s, not 10 (and its liveliness token goes)."""
RETRY_S = 1.0
"""A browser that lost its robot tries its endpoint again at least this often (Zenoh
backs off up to 4 s by default)."""


def check_endpoint(endpoint: str, *, key: str = "zenoh") -> str:
    """``proto/address`` (``tcp/127.0.0.1:7447``, ``tcp/[::1]:7447``, ``udp/...``)."""
    proto, sep, address = endpoint.strip().partition("/")
    if not sep or not proto or not address:
        raise InputError(f"{endpoint!r}: a Zenoh endpoint is PROTOCOL/ADDRESS, e.g. "
                         f"{DEFAULT_ENDPOINT}", key=key)
    return endpoint.strip()


def config(*, listen: list[str] | None = None, connect: list[str] | None = None,
           file: str | Path | None = None, connect_timeout_s: float | None = None,
           ) -> zenoh.Config:
    """A session's configuration: ``file`` (a Zenoh JSON5 file) or the defaults, peer
    mode, a lease of :data:`LEASE_S` and retries every :data:`RETRY_S`; ``listen`` and
    ``connect`` replace the endpoints where given; multicast scouting off.
    ``connect_timeout_s``: opening fails when no connect endpoint answers that soon (a
    browser: no robot there)."""
    if file is not None:
        try:
            c = zenoh.Config.from_file(str(file))
        except (OSError, zenoh.ZError, ValueError) as err:
            raise InputError(f"{file}: not a Zenoh configuration: {err}",
                             key="zenoh_config") from None
    else:
        c = zenoh.Config()
        c.insert_json5("mode", json.dumps("peer"))
        c.insert_json5("transport/link/tx/lease", str(int(LEASE_S * 1000)))
        c.insert_json5("connect/retry", json.dumps({
            "period_init_ms": int(RETRY_S * 500), "period_max_ms": int(RETRY_S * 1000),
            "period_increase_factor": 2}))
        if listen is None:
            listen = []
        if connect is None:
            connect = []
    c.insert_json5("scouting/multicast/enabled", "false")
    if listen is not None:
        c.insert_json5("listen/endpoints", json.dumps(listen))
    if connect is not None:
        c.insert_json5("connect/endpoints", json.dumps(connect))
    if connect_timeout_s is not None and connect:
        c.insert_json5("connect/exit_on_failure", "true")
        c.insert_json5("connect/timeout_ms", str(max(1, int(connect_timeout_s * 1000))))
    return c


def open_session(c: zenoh.Config, what: str) -> zenoh.Session:
    """:func:`zenoh.open`; BusError naming ``what`` (the endpoint) where it fails."""
    try:
        return zenoh.open(c)
    except zenoh.ZError as err:
        text = str(err).split(" at /", 1)[0]  # not the engine's source paths
        raise BusError(f"Zenoh on {what}: {text}") from None


def address_in_use(err: BusError) -> bool:
    return "in use" in str(err)
