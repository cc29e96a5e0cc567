"""Asking a running ``ucom fleet serve`` to inject a fault (``ucom fleet fault``): one
control connection on its socketcand port, the ``< ucom_fault ... >`` element of
:mod:`ucom_tools.wire.socketcand_fault`, its answer; every wait with a deadline."""

from __future__ import annotations

import socket
import time
from typing import Final

from ucom_tools.errors import BusError, InputError
from ucom_tools.wire.socketcand import ElementError, ElementSplitter
from ucom_tools.wire.socketcand_fault import answer, fault_element

TIMEOUT_S: Final = 15.0
"""How long the whole request may take (the server gives its bus processes 10 s)."""


def request_fault(host: str, port: int, target: str, kind: str, seconds: float | None,
                  timeout: float = TIMEOUT_S) -> str:
    """Ask the fleet served on ``host``:``port`` to inject ``kind`` on ``target`` for
    ``seconds`` (None: the kind's default) at once; returns what it did, in a sentence.
    :class:`InputError` when it refused (a bus or board it lacks: nothing was done),
    :class:`BusError` when it cannot be reached, does not answer in ``timeout`` seconds,
    is no fleet that takes faults, or could not apply it."""
    where = f"{host}:{port}"
    deadline = time.monotonic() + timeout
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as err:
        raise BusError(f"cannot connect to {where}: {err.strerror or err}") from None
    with sock:
        splitter = ElementSplitter()

        def next_element(what: str) -> bytes:
            while (element := splitter.next()) is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise BusError(f"{where} did not answer {what} in {timeout:g} s")
                sock.settimeout(left)
                try:
                    chunk = sock.recv(4096)
                except TimeoutError:
                    continue
                except OSError as err:
                    raise BusError(f"the connection to {where} failed: "
                                   f"{err.strerror or err}") from None
                if not chunk:
                    raise BusError(f"{where} closed the connection before it answered "
                                   f"{what}")
                try:
                    splitter.feed(chunk)
                except ElementError as err:
                    raise BusError(f"{where} does not speak socketcand: {err}") from None
            return element

        greeting = next_element("with < hi >")
        if greeting.split() != [b"hi"]:
            raise BusError(f"{where} does not speak socketcand: it greeted "
                           f"< {greeting.decode('ascii', 'replace')} >")
        try:
            sock.sendall(fault_element(target, kind, seconds))
        except OSError as err:
            raise BusError(f"the connection to {where} failed: {err.strerror or err}") \
                from None
        outcome, text = answer(next_element("the fault"))
    if outcome == "ok":
        return text
    if outcome == "refused":
        raise InputError(f"{where} refused it: {text}")
    if outcome == "failed":
        raise BusError(f"{where} could not apply the fault: {text}")
    raise BusError(f"{where} does not take faults (no ucom fleet serve?): it answered "
                   f"< {text} >")
