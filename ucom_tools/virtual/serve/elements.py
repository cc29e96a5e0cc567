"""What ``ucom fleet serve`` answers to a client's elements before raw mode, the same
from one process (:class:`~ucom_tools.virtual.serve.connection.Connection`) and from the
main process of a multi-process server
(:mod:`~ucom_tools.virtual.serve.multiserve_dispatch`): ``< open BUS >``
(:func:`check_open`), an injected fault (``< ucom_fault ... >``, :func:`inject_element`),
an unknown command (:func:`unsupported`), a frame before a bus is open
(:data:`NO_BUS_OPEN`); and a client's address as the log writes it (:func:`peer_name`).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from typing import Any

from ucom_tools.config.scenario import injected
from ucom_tools.errors import InputError, UcomError
from ucom_tools.wire import socketcand_fault
from ucom_tools.wire.socketcand import ElementError, quote

NO_BUS_OPEN = "no bus open: send < open BUS > first"
"""The answer to ``rawmode`` and ``send`` before a bus is open."""


def check_open(args: list[str], buses: Collection[str], fleet_name: str,
               already_open: str | None = None) -> str:
    """The bus that ``< open BUS >`` (the words after ``open``) names; ElementError with
    the server's answer when it is malformed, a bus is open already, or no such bus."""
    if len(args) != 1:
        raise ElementError("usage: open BUS")
    if already_open is not None:
        raise ElementError(f"bus {already_open} is already open")
    if args[0] not in buses:
        raise ElementError(f"no bus {quote(args[0])} in {fleet_name}")
    return args[0]


def inject_element(args: list[str], inject: Callable[..., str]) -> str:
    """Apply ``< ucom_fault TARGET KIND [SECONDS] >`` (the words after the command) with
    ``inject(fault)`` (:meth:`Fleet.inject`, or a multi-process server's routing) and
    return the answer ``< ok TEXT >``; ElementError with the refusal or failure."""
    target, kind, seconds = socketcand_fault.parse_fault(args)
    try:
        text = inject(injected(kind, target, seconds))
    except InputError as err:
        raise ElementError(socketcand_fault.refusal(str(err))) from None
    except UcomError as err:
        raise ElementError(socketcand_fault.refusal(str(err), failed=True)) from None
    return socketcand_fault.ok_element(text)


def unsupported(verb: str) -> ElementError:
    """The answer to an element with an unknown command word."""
    return ElementError(f"unsupported command {quote(verb)}")


def peer_name(address: Any) -> str:
    """A client's address as people write it: ``127.0.0.1:40000``, ``[::1]:40000``."""
    if isinstance(address, tuple) and len(address) >= 2:
        host = str(address[0])
        return f"[{host}]:{address[1]}" if ":" in host else f"{host}:{address[1]}"
    return str(address)
