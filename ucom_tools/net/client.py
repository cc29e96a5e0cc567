"""The other side of :mod:`.share`: a running robot's edges from another host
(``ucom browse``; ``man/ucom-network.7``).

::

    from ucom_tools.net.client import RobotClient

    with RobotClient.connect("tcp/127.0.0.1:7447") as robot:      # the only robot there
        print(robot.read(["Right Eye Joint Sensor"]))             # {name: (t, value)}
        print(robot.read()["Right Eye Joint Sensor"].valid)       # False: its board is lost
        robot.write("Right Eye Target", 1000)                     # needs --allow-writes
        sub = robot.subscribe(["Right Eye Joint Sensor"], print)  # print(t, name, value)

Names are resolved as the robot resolves them (``Prefix/Unique`` or a unique name that
only one board uses, case does not matter), from the robot's structure.  Errors are the
project's: :class:`~ucom_tools.errors.BusError` where no robot answers,
:class:`~ucom_tools.errors.InputError` for a name or a value the robot refused (the
range, the closest names), :class:`WritesForbidden` where it does not take writes.
"""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import zenoh

from ucom_tools.edgelists.model import EdgeKind, EdgeSpec
from ucom_tools.errors import BusError, InputError, UcomError
from ucom_tools.net import keys
from ucom_tools.net.session import check_endpoint, config, open_session
from ucom_tools.net.share import origin
from ucom_tools.ops.edges import EdgeRef, Names
from ucom_tools.wire import mca

JSON = zenoh.Encoding.APPLICATION_JSON
ANSWER_S = 5.0
"""How long a write or a read waits for the robot's answer."""

Callback = Callable[..., None]
"""``callback(t, name, value)``, with ``valid`` after them where asked for."""


class Reading(tuple[float, Any]):
    """An edge's latest value as :meth:`RobotClient.read` gives it: a ``(t, value)`` pair
    that also says whether it is current (:attr:`valid`: False where its board is lost,
    ``man/ucom-network.7``; the value is then the last before the loss) and since when
    its board is lost (:attr:`lost_since`, on the base of ``t``)."""

    valid: bool
    lost_since: float | None
    seen: str

    def __new__(cls, t: float, value: Any, valid: bool = True,
                lost_since: float | None = None, seen: str = "") -> Reading:
        self = super().__new__(cls, (t, value))
        self.valid, self.lost_since, self.seen = valid, lost_since, seen
        return self

    @property
    def t(self) -> float:
        return float(self[0])

    @property
    def value(self) -> Any:
        return self[1]

    @property
    def age(self) -> float | None:
        """Of a stale value: how old it was when its board was lost (None: valid)."""
        return None if self.lost_since is None else self.lost_since - self.t


def reading_of(doc: dict[str, Any], t: float, value: Any) -> Reading:
    """A value of a board's ``values`` sample ``doc``, with the sample's validity."""
    lost = doc.get("lost") if isinstance(doc.get("lost"), dict) else None
    return Reading(t, value, doc.get("valid", True) is not False,
                   None if lost is None else lost.get("since"),
                   "" if lost is None else str(lost.get("seen", "")))


class WritesForbidden(UcomError):
    """The robot's loop runs without ``--allow-writes``: nothing is written from here."""


class RobotGone(BusError):
    """The robot's liveliness token went away (its loop ended or its host is gone)."""


class Subscription:
    """Values of some edges as they come (:meth:`RobotClient.subscribe`); :meth:`close`
    ends it."""

    def __init__(self, subscribers: list[Any]) -> None:
        self._subscribers = subscribers

    def close(self) -> None:
        for s in self._subscribers:
            s.undeclare()
        self._subscribers = []


def _refs(structure: dict[str, Any]) -> list[tuple[EdgeRef, str]]:
    """The robot's edges (and their keys) as :class:`EdgeRef`: named and checked as the
    robot names and checks them."""
    out = []
    for bus in structure.get("buses", []):
        for b in bus["boards"]:
            counts: dict[mca.Kind, int] = {}
            for e in b["edges"]:
                kind = mca.Kind[e["kind"]]
                index = counts.get(kind, 0)
                counts[kind] = index + 1
                enc = e["encoding"]
                spec = EdgeSpec(EdgeKind(kind), e["generic"], width=enc["width"],
                                signed=enc["signed"], exponent=enc["exponent"],
                                minimum=enc["raw_min"], maximum=enc["raw_max"],
                                unit=e["unit"],
                                default=min(max(0, enc["raw_min"]), enc["raw_max"]))
                out.append((EdgeRef(bus["name"], b["board"], b["where"], b["prefix"],
                                    e["name"], e["generic"], kind, index, spec), e["key"]))
    return out


class RobotClient:
    """One robot's run time, from another host (see the module docstring)."""

    def __init__(self, session: zenoh.Session, robot: str, structure: dict[str, Any],
                 where: str) -> None:
        self.session = session
        self.robot = robot
        """The robot's chunk of the keys (``armar3``)."""
        self.structure = structure
        """The robot's ``ucom/<robot>/structure`` document."""
        self.where = where
        pairs = _refs(structure)
        self.names = Names(r for r, _ in pairs)
        self._keys = {r: k for r, k in pairs}
        self._by_edge = {(r.bus, r.board, r.unique): r for r, _ in pairs}

    @classmethod
    def connect(cls, endpoint: str | None = keys.DEFAULT_ENDPOINT, *, robot: str | None = None,
                config_file: str | Path | None = None, timeout: float = 5.0) -> RobotClient:
        """Connect to ``endpoint`` (a peer, no multicast) and find ``robot`` there (or the
        only robot there) within ``timeout`` seconds: BusError naming the endpoint where
        none answers."""
        where = check_endpoint(endpoint) if endpoint is not None else str(config_file)
        deadline = time.monotonic() + timeout
        try:
            s = open_session(config(listen=[], connect=[where] if endpoint else None,
                                    file=config_file, connect_timeout_s=timeout), where)
        except BusError:
            raise BusError(f"no robot on {where}: nothing answers there (is a robot's loop "
                           "shared on the network, on that address?)") from None
        try:
            name = cls._find(s, robot, where, deadline, timeout)
            structure = cls._structure(s, name, where, deadline)
            return cls(s, name, structure, where)
        except BaseException:
            s.close()
            raise

    @staticmethod
    def _find(s: zenoh.Session, robot: str | None, where: str, deadline: float,
              timeout: float) -> str:
        pattern = keys.robot_key(robot, "alive") if robot else "ucom/*/alive"
        while True:
            found = sorted({keys.unescape(str(r.ok.key_expr).split("/")[1])
                            for r in s.liveliness().get(pattern, timeout=0.5)
                            if r.ok is not None})
            if robot is not None and robot in found:
                return robot
            if robot is None and len(found) == 1:
                return found[0]
            if robot is None and len(found) > 1:
                raise InputError(f"{len(found)} robots on {where}: {', '.join(found)}; name "
                                 "one", key="ROBOT")
            if time.monotonic() >= deadline:
                which = f"robot {robot!r}" if robot else "ucom robot"
                raise BusError(f"no {which} on {where} within {timeout:g} s")
            time.sleep(0.05)  # the robot's declarations may still be on their way

    @staticmethod
    def _structure(s: zenoh.Session, robot: str, where: str, deadline: float,
                   ) -> dict[str, Any]:
        why = "it did not answer"
        while time.monotonic() < deadline:
            for r in s.get(keys.robot_key(robot, "structure"),
                           timeout=max(0.1, deadline - time.monotonic())):
                if r.ok is not None:
                    return keys.loads(r.ok.payload.to_bytes())
                if r.err is not None:
                    why = str(keys.loads(r.err.payload.to_bytes()).get("message", why))
            time.sleep(0.05)  # "starting": the boards are being checked
        raise BusError(f"robot {robot!r} on {where} gave no structure: {why}")

    # ------------------------------------------------------------------ values
    def resolve(self, name: str) -> EdgeRef:
        """The edge called ``name`` (InputError with the closest names otherwise)."""
        return self.names.resolve(name)

    def read(self, names: Sequence[str] | None = None, *, timeout: float = ANSWER_S,
             ) -> dict[str, Reading]:
        """The latest values (time stamp, value; a :class:`Reading`, which also says
        whether the value is current) by robot-wide name: of ``names``, or of every edge
        that has one.  Waits up to ``timeout`` for boards that have published nothing yet
        (a robot that just started)."""
        wanted = [self.resolve(n) for n in names] if names is not None else None
        deadline = time.monotonic() + timeout
        while True:
            got: dict[EdgeRef, Reading] = {}
            for r in self.session.get(f"ucom/{keys.escape(self.robot)}/*/*/values",
                                      timeout=max(0.1, deadline - time.monotonic())):
                if r.ok is None:
                    continue
                doc = keys.loads(r.ok.payload.to_bytes())
                for unique, value in doc["values"].items():
                    ref = self._by_edge.get((doc["bus"], doc["board"], unique))
                    if ref is not None:
                        got[ref] = reading_of(doc, doc["t"], value)
            missing = [r for r in wanted or () if r not in got]
            if (got and not missing) or time.monotonic() >= deadline:
                break
            time.sleep(0.05)  # nothing published yet: the robot is starting
        if missing:
            raise BusError(f"robot {self.robot!r} on {self.where} has no value of "
                           + ", ".join(self.names.name_of(r) for r in missing)
                           + f" within {timeout:g} s")
        refs = wanted if wanted is not None else [r for r in self.names if r in got]
        return {self.names.name_of(r): got[r] for r in refs}

    def write(self, name: str, value: int | float | str, *, timeout: float = ANSWER_S,
              ) -> dict[str, Any]:
        """Set a CI or PAR on the robot, checked there as a local set is: its answer
        (``{"ok": true, "name": ..., "value": ...}``).  InputError where the robot refused
        the name or value (the range, the closest names), WritesForbidden where it takes no
        writes, BusError where it did not answer."""
        return self._ask("set", {"name": name, "value": value, "origin": origin()},
                         timeout)

    def stop(self, *, timeout: float = ANSWER_S) -> dict[str, Any]:
        """Stop the robot's boards (motors off) and its loop; needs ``--allow-writes``
        there."""
        return self._ask("stop", {"origin": origin()}, timeout)

    def _ask(self, what: str, doc: dict[str, Any], timeout: float) -> dict[str, Any]:
        for r in self.session.get(keys.robot_key(self.robot, what), payload=keys.dumps(doc),
                                  encoding=JSON, timeout=timeout):
            if r.ok is not None:
                return keys.loads(r.ok.payload.to_bytes())
            if r.err is not None:
                answer = keys.loads(r.err.payload.to_bytes())
                message = str(answer.get("message", "refused"))
                if answer.get("error") == "forbidden":
                    raise WritesForbidden(message)
                if answer.get("error") == "refused":
                    raise InputError(message, key=str(doc.get("name") or what))
                raise UcomError(f"robot {self.robot!r}: {message}")
        raise BusError(f"robot {self.robot!r} on {self.where} did not answer within "
                       f"{timeout:g} s")

    def subscribe(self, names: Sequence[str], callback: Callback, *,
                  validity: bool = False) -> Subscription:
        """``callback(t, name, value)`` for each value of the edges ``names`` as the robot
        publishes it (it publishes an edge's own key only while someone subscribes); with
        ``validity``, ``callback(t, name, value, valid)`` (False: its board is lost, the
        value is the last before the loss)."""
        subscribers = []
        for n in names:
            ref = self.resolve(n)
            shown = self.names.name_of(ref)

            def on_sample(sample: zenoh.Sample, shown: str = shown) -> None:
                try:
                    doc = keys.loads(sample.payload.to_bytes())
                except ValueError:
                    return
                if validity:
                    callback(doc["t"], shown, doc["value"], doc.get("valid", True) is not False)
                else:
                    callback(doc["t"], shown, doc["value"])
            subscribers.append(self.session.declare_subscriber(self._keys[ref], on_sample))
        return Subscription(subscribers)

    def on_gone(self, callback: Callable[[], None]) -> Subscription:
        """``callback()`` when the robot's liveliness token goes (its loop ended, its host
        died or the network between is gone): :meth:`on_alive` for the going only."""
        return self.on_alive(lambda up: None if up else callback())

    def on_values(self, callback: Callable[[dict[str, Any]], None]) -> Subscription:
        """``callback(doc)`` for each board's sample as the robot publishes it (one per board
        and publishing period: the ``values`` payload of ``man/ucom-network.7``, with "bus",
        "board", "t" and "values" by unique name); a sample that is not ours is dropped."""
        return self._documents(self._every_board("values"), callback)

    def on_events(self, callback: Callable[[dict[str, Any]], None]) -> Subscription:
        """``callback(doc)`` for each of the run's events (``ucom/<robot>/events``: the
        loop's state, a board's Error, a write or stop from the network)."""
        return self._documents(keys.robot_key(self.robot, "events"), callback)

    def on_boards(self, callback: Callable[[str, int, bool], None]) -> Subscription:
        """``callback(bus, board, running)`` for each board's liveliness token: True when it
        is there (also for the tokens already there), False when it goes (the loop ended,
        or the board's watchdog stopped its motors)."""
        def on_sample(sample: zenoh.Sample) -> None:
            parts = str(sample.key_expr).split("/")
            try:
                bus, board = keys.unescape(parts[2]), int(parts[3])
            except (IndexError, ValueError):
                return
            callback(bus, board, sample.kind != zenoh.SampleKind.DELETE)
        return Subscription([self.session.liveliness().declare_subscriber(
            self._every_board("board_alive"), on_sample, history=True)])

    def on_status(self, callback: Callable[[dict[str, Any]], None]) -> Subscription:
        """``callback(doc)`` for each board's Status report as the robot asks for them
        (about once a second a board: the ``status`` payload of ``man/ucom-network.7``,
        with "bus", "board", "t", "state", "leds" (red, yellow, green: on, off, blink),
        "tec", "rec", "overruns")."""
        return self._documents(self._every_board("status"), callback)

    def _every_board(self, what: str) -> str:
        """The key of ``what`` (values, status, board_alive) of every board of the robot."""
        return keys.KEYS[what].format(robot=keys.escape(self.robot), bus="*", board="*")

    def _documents(self, key: str, callback: Callable[[dict[str, Any]], None],
                   ) -> Subscription:
        """``callback(doc)`` for each sample on ``key`` that is one of our JSON documents
        (any other is dropped)."""
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                doc = keys.loads(sample.payload.to_bytes())
            except ValueError:
                return
            callback(doc)
        return Subscription([self.session.declare_subscriber(key, on_sample)])

    def on_alive(self, callback: Callable[[bool], None]) -> Subscription:
        """``callback(False)`` when the robot's liveliness token goes ("connection lost":
        its loop ended, its host died or the network between is gone), ``callback(True)``
        when it is there (at once where it is, and again when the robot or the network
        comes back: the session reconnects by itself)."""
        def on_sample(sample: zenoh.Sample) -> None:
            callback(sample.kind != zenoh.SampleKind.DELETE)
        return Subscription([self.session.liveliness().declare_subscriber(
            keys.robot_key(self.robot, "alive"), on_sample, history=True)])

    def alive(self) -> bool:
        """Is the robot's liveliness token there now?"""
        return any(r.ok is not None for r in self.session.liveliness().get(
            keys.robot_key(self.robot, "alive"), timeout=1.0))

    def watch(self, names: Sequence[str], seconds: float | None = None, *,
              validity: bool = False) -> Iterator[tuple[Any, ...]]:
        """Yield (t, name, value) of ``names`` as they come, for ``seconds`` (None: until
        the caller stops); with ``validity`` (t, name, value, valid); RobotGone where the
        robot goes away meanwhile."""
        q: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        sub = self.subscribe(names, lambda *item: q.put(item), validity=validity)
        gone = self.on_gone(lambda: q.put(None))
        end = None if seconds is None else time.monotonic() + seconds
        try:
            while True:
                left = 0.5 if end is None else end - time.monotonic()
                if left <= 0:
                    return
                try:
                    item = q.get(timeout=min(0.5, left))
                except queue.Empty:
                    continue
                if item is None:
                    raise RobotGone(f"robot {self.robot!r} is gone from {self.where}")
                yield item
        finally:
            sub.close()
            gone.close()

    # ------------------------------------------------------------------ the end
    def close(self) -> None:
        """Close the session (a process that does not, does not end)."""
        self.session.close()

    def __enter__(self) -> RobotClient:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
