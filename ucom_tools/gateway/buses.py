"""The gateway's CANopen buses as ``--canopen`` names them, and opening them.

``[UCOM_BUS[,UCOM_BUS...]=]INTERFACE:CHANNEL``: any python-can interface and channel
(``socketcan:vcan0``, ``pcan:PCAN_USBBUS1``, ``virtual:co`` in one process), or
``socketcand:CHANNEL@HOST:PORT`` for a socketcand server (a bus that ``ucom fleet serve
--extra-bus CHANNEL`` serves; ucom's own socketcand client).  The UCoM buses in front put
their joints on this bus; a spec without them takes every joint no other spec names.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

import can

from ucom_tools.errors import BusError, InputError

_SPEC = re.compile(r"^(?:(?P<ucom>[A-Za-z0-9_.-]+(?:,[A-Za-z0-9_.-]+)*)=)?"
                   r"(?P<interface>[A-Za-z0-9_]+):(?P<channel>.+)$")
_SOCKETCAND = re.compile(r"^(?P<channel>[^@]+)@(?P<host>[^:@]+|\[[0-9a-fA-F:]+\]):"
                         r"(?P<port>[0-9]{1,5})$")


@dataclass(frozen=True)
class CanopenSpec:
    """One ``--canopen`` value, parsed."""

    text: str
    interface: str
    channel: str
    ucom_buses: tuple[str, ...] = ()
    host: str | None = None
    port: int | None = None

    @property
    def where(self) -> str:
        """The bus without the UCoM buses in front ('socketcand:CO0@127.0.0.1:29536')."""
        return self.text.split("=", 1)[1] if self.ucom_buses else self.text


def parse(text: str, *, key: str = "canopen") -> CanopenSpec:
    """A CANopen bus as text; InputError saying the form where it does not fit."""
    m = _SPEC.match(text.strip())
    if m is None:
        raise InputError(f"'{text}': expected [UCOM_BUS=]INTERFACE:CHANNEL, e.g. "
                         "socketcan:vcan0, socketcand:CO0@127.0.0.1:29536 or "
                         "CAN0=socketcan:vcan0", key=key)
    ucom = tuple(m["ucom"].split(",")) if m["ucom"] else ()
    interface, channel = m["interface"], m["channel"]
    if interface == "socketcand":
        s = _SOCKETCAND.match(channel)
        if s is None:
            raise InputError(f"'{text}': a socketcand bus is socketcand:CHANNEL@HOST:PORT, "
                             "e.g. socketcand:CO0@127.0.0.1:29536", key=key)
        port = int(s["port"])
        if not 1 <= port <= 65535:
            raise InputError(f"'{text}': port {port} is not 1..65535", key=key)
        return CanopenSpec(text, interface, s["channel"], ucom, s["host"].strip("[]"), port)
    return CanopenSpec(text, interface, channel, ucom)


def check(specs: Sequence[CanopenSpec], ucom_buses: Sequence[str], *,
          key: str = "canopen") -> None:
    """The specs together: each UCoM bus named once and known, at most one spec without
    UCoM buses, every bus opened once."""
    if not specs:
        raise InputError("the gateway needs a CANopen bus, e.g. "
                         "socketcand:CO0@127.0.0.1:29536", key=key)
    seen: dict[str, str] = {}
    catch_all = [s for s in specs if not s.ucom_buses]
    if len(catch_all) > 1:
        raise InputError(f"'{catch_all[1].text}': only one CANopen bus may leave out its UCoM "
                         f"buses (it takes every joint the others do not; "
                         f"'{catch_all[0].text}' does already)", key=key)
    where: dict[str, str] = {}
    for s in specs:
        if s.where in where:
            raise InputError(f"'{s.text}': {s.where} is given twice (once with UCoM buses "
                             "CAN0,CAN1=... puts several on one CANopen bus)", key=key)
        where[s.where] = s.text
        for bus in s.ucom_buses:
            if bus not in ucom_buses:
                raise InputError(f"'{s.text}': the robot has no bus {bus} (its buses: "
                                 f"{', '.join(ucom_buses)})", key=key)
            if bus in seen:
                raise InputError(f"'{s.text}': {bus}'s joints are on '{seen[bus]}' already",
                                 key=key)
            seen[bus] = s.text
    if not catch_all:
        missing = [b for b in ucom_buses if b not in seen]
        if missing:
            raise InputError(f"the joints of {', '.join(missing)} have no CANopen bus: "
                             "name them with a CANopen bus, or give one CANopen bus "
                             "without UCoM buses for the rest", key=key)


class Carries(Protocol):
    """A CANopen bus as far as which joints it carries: its UCoM buses (none: the rest)."""

    @property
    def ucom_buses(self) -> tuple[str, ...]: ...


B = TypeVar("B", bound=Carries)
J = TypeVar("J")


def by_bus(specs: Sequence[B], joints: Iterable[J], ucom_bus_of: Callable[[J], str]
           ) -> dict[int, list[J]]:
    """Which joints each CANopen bus carries (index in ``specs`` -> joints, in order): the
    bus that names a joint's UCoM bus, else the one that names none."""
    named = {b: i for i, s in enumerate(specs) for b in s.ucom_buses}
    rest = next((i for i, s in enumerate(specs) if not s.ucom_buses), None)
    out: dict[int, list[J]] = {i: [] for i in range(len(specs))}
    for j in joints:
        i = named.get(ucom_bus_of(j), rest)
        if i is not None:
            out[i].append(j)
    return out


def open_bus(spec: CanopenSpec, *, connect_timeout: float = 5.0) -> can.BusABC:
    """The python-can bus of ``spec``; BusError saying why it cannot be opened."""
    try:
        if spec.interface == "socketcand":
            from ucom_tools.transport.socketcand import SocketcandBus

            assert spec.host is not None and spec.port is not None
            return SocketcandBus(spec.channel, spec.host, spec.port,
                                 connect_timeout=connect_timeout)
        return can.Bus(interface=spec.interface, channel=spec.channel)
    except BusError:
        raise
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as err:
        raise BusError(f"CANopen bus {spec.text}: cannot open the bus: {err}") from err


__all__ = ["CanopenSpec", "Carries", "by_bus", "check", "open_bus", "parse"]
