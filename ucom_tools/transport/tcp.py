"""A TCP connection made within a deadline, for the network buses (socketcand): every
address of the host tried in turn until the deadline, without Nagle's algorithm (a bus
writes many small elements), non-blocking once made."""

from __future__ import annotations

import contextlib
import selectors
import socket
import time

import can


def connect(host: str, port: int, timeout: float, where: str) -> socket.socket:
    """A non-blocking TCP connection with TCP_NODELAY, made within ``timeout`` seconds;
    :class:`can.CanInitializationError` naming ``where`` if none was."""
    deadline = time.monotonic() + timeout
    error: OSError | None = None
    try:
        addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, OverflowError) as err:
        raise can.CanInitializationError(
            f"cannot connect to socketcand {where}: {reason(err)}") from err
    for family, kind, proto, _, address in addresses:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        sock = socket.socket(family, kind, proto)
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(remaining)
            sock.connect(address)
        except OSError as err:
            sock.close()
            error = err
            continue
        sock.setblocking(False)
        return sock
    if error is None or isinstance(error, TimeoutError):
        why = f"no connection within {timeout:g} s"
    else:
        why = reason(error)
    raise can.CanInitializationError(f"cannot connect to socketcand {where}: {why}") from error


def reason(err: Exception) -> str:
    """What went wrong, in the operating system's words where it has them."""
    return (err.strerror if isinstance(err, OSError) else None) or str(err) or type(err).__name__


def send_within(sock: socket.socket, writable: selectors.BaseSelector, data: bytes,
                deadline: float) -> int:
    """Write ``data`` to the non-blocking ``sock`` (registered for writing in
    ``writable``) until all of it is written or ``deadline`` (``time.monotonic()``) has
    passed; the bytes written.  ``OSError`` (and ``ValueError``: the socket closed
    meanwhile) as the socket raises them."""
    try:  # the usual case: the socket takes all of it at once (no context manager:
        sent = sock.send(data)  # ~1 us per cycle)
    except BlockingIOError:
        sent = 0
    if sent == len(data):
        return sent
    view = memoryview(data)
    while sent < len(data):
        remaining = deadline - time.monotonic()
        if remaining <= 0 or not writable.select(remaining):
            break
        with contextlib.suppress(BlockingIOError):
            sent += sock.send(view[sent:])
    return sent
