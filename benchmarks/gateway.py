#!/usr/bin/env python3
"""The CANopen gateway at work (issue 35): ARMAR-III's 27 joints as CiA 402 drives on four
CANopen buses (one per UCoM bus) beside the 1 kHz UCoM loop, each bus driven by a master
in a process of its own at a SYNC rate of 100 Hz and of 250 Hz.

``ucom fleet serve armar3 --extra-bus CO0 ... CO3`` (armar3.fl.S flashed) serves the
robot and the four CANopen buses; in turns, ``ucom remote run armar3 -i socketcand ...
--on-fault hold --for T --json`` (the baseline) and ``ucom gateway canopen armar3 ...
--canopen CAN0=socketcand:CO0@127.0.0.1:PORT ... --on-fault hold --for T --json`` with
one master per CANopen bus (``--master``: this file in a process of its own, python-can's
own socketcand client, ``tcp_tune``).  A master waits for its nodes' heartbeats, starts
them (NMT), sends SYNC at the rate, puts every joint in cyclic synchronous position
(0x6060 = 8, controlword 0x06/0x07/0x0F by SDO, each step awaited in the statusword of
TPDO1), then for ``--seconds`` sends each joint's 0x607A (a slow sine of 100 counts about
where it stood) and 0x60FF by RPDO2 half a period after each SYNC, and an SDO upload every
20 ms (0x6064 and the joint's first SO object 0x4000-, in turns over its nodes).

Figures, per SYNC rate (``rates``; every bus's pooled):

- ``sync_tpdo_p50_ms`` / ``_p99_ms`` / ``_max_ms``: from the SYNC's send (the master's
  clock, just before the call) to the end on the bus of the last TPDO of that SYNC (the
  frame's time stamp, as python-can gives it: the served bus stamps each frame with the
  end of its transmission, on the wall clock): the 2 a node-th TPDO after it, so that a
  SYNC whose TPDOs spill past the next one counts its whole time; every SYNC counts;
  ``sync_tpdo_arrival_p99_ms``: the same to its arrival in the master's receiving
  thread; ``complete_pct``: SYNCs whose every TPDO (2 a node) came before the next SYNC;
- ``sdo_p50_ms`` / ``sdo_p99_ms`` / ``sdo_max_ms``: SDO upload round trips (request sent
  to answer received), ``sdo_timeouts`` (none within 50 ms);
- ``cpu_us_per_joint_sync``: the gateway's CPU on SYNCs (RPDOs applied, its drives run,
  TPDOs built and sent: its runtimes' ``sync_cpu_s``) per joint and SYNC;
  ``thread_cpu_us_per_joint_sync`` all of its runtimes' threads' CPU, idle turns included;
- ``lateness_p99_ms`` and ``missed`` of the loop with the gateway, ``baseline_p99_ms`` and
  ``baseline_missed`` of the baseline run just before it, ``lateness_ratio``;
- ``bits_per_sync`` of SYNC + TPDOs + RPDOs on each CANopen bus, counted from the frames
  the master saw (stuff bits included, ``ucom_tools.wire.canbits.frame_bits``), and the
  bus load at the rate against 1 Mbit/s: ``load_pct`` (counted), ``load_nominal_pct`` and
  ``load_worst_pct`` (47 + 8n bits a frame, and with every stuff bit it can need: as
  ``remote`` computes the UCoM buses' planned load); ``configured_worst_pct``: the product's
  ``pdo_load`` of the nodes' PDO configuration (every RPDO every SYNC: an upper bound);
- ``enabled``: joints in OPERATION ENABLED at the start of the measurement (of 27),
  ``emcys``: EMCY frames seen meanwhile; ``watchdog_stops``: boards the watchdog stopped
  (the loop kept from its cycles for 50 ms), in the baseline and with the gateway, whose
  run is then repeated once (``attempts``: the figures are the last run's);
  ``writes_applied`` / ``writes_refused``: the gateway's writes to the loop.

Targets (``targets_met``; MET or NOT MET in the text, exit 1 when one is not), at each
rate: SYNC to the last TPDO p99 <= 2 ms; SDO upload p99 <= 5 ms (ros2_canopen's default
SDO timeout is 20 ms); the loop's lateness p99 with the gateway <= 1.2 x without; every
joint enabled and at least 99 % of the SYNCs complete; no watchdog stop.  ``--json``
prints the figures as one JSON object; ``--quick`` measures 3 s at each rate.  On the
development machine (2 cores) everything above shares two processors: ``cores`` says how
many this machine has.  ``--buses N`` puts only the first N UCoM buses' joints on CANopen
buses (``canopen_buses``; one master each; the other joints' nodes on a bus of their
own that no master drives): what the gateway's path costs where the machine is not
saturated by four masters beside the served fleet.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.consumers import served_armar3  # noqa: E402
from benchmarks.lib.canopen_master import Master, MasterSpec  # noqa: E402
from benchmarks.runtime import percentile  # noqa: E402
from ucom_tools import compiled  # noqa: E402
from ucom_tools.gateway import dictionary, joints  # noqa: E402
from ucom_tools.gateway.load import pdo_load  # noqa: E402
from ucom_tools.signals import stop_signals  # noqa: E402

BUSES = ("CAN0", "CAN1", "CAN2", "CAN3")
"""ARMAR-III's UCoM buses; CANopen bus COn carries the joints of CANn."""
RATES = (100.0, 250.0)
SETUP_S = 10.0
"""What a gateway run lasts beyond the measurement: its nodes boot once the boards run
(a few seconds after the command starts), then the masters set their joints up."""
START_S = 60.0
"""How long a run may take to start, and a master to find its nodes."""
BITRATE = 1_000_000
ATTEMPTS = 2
"""Gateway runs at a rate, where the boards' watchdog stopped them in the first (the
loop kept from its cycles for 50 ms: see ``attempts``)."""


def ucom(*args: str) -> list[str]:
    return [sys.executable, "-m", "ucom_tools", *args]


@contextlib.contextmanager
def served() -> Iterator[int]:
    """ARMAR-III with armar3.fl.S flashed and the CANopen buses CO0-CO3, served by ``ucom
    fleet serve`` in a session of its own (``benchmarks/consumers.py``); its port."""
    extra = [a for n in range(len(BUSES)) for a in ("--extra-bus", f"CO{n}")]
    with served_armar3(*extra) as port:
        yield port


def stop(proc: subprocess.Popen[Any], timeout: float = 10.0) -> None:
    """SIGINT, then killed where it does not end within ``timeout``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def connection(port: int, realtime: bool) -> list[str]:
    """The robot over the served fleet; ``--on-fault hold``: a served fleet that a busy
    machine holds up for 5 ms makes its boards look lost, which would end the run."""
    return ["armar3", "-i", "socketcand", "--host", "127.0.0.1", "--port", str(port),
            "--on-fault", "hold", *(["--realtime"] if realtime else [])]


def loop_figures(doc: dict[str, Any], stderr: str) -> dict[str, Any]:
    """The loop's figures of a run's ``--json``; where it has none, why (its stderr)."""
    run = doc.get("run", {})
    return {"p99_ms": run.get("jitter_ms", {}).get("p99"), "missed": run.get("missed"),
            "cycles": run.get("cycles"), "error": None if run else stderr[-800:],
            "watchdog_stops": sum(bool(e.get("stopped_motors"))
                                  for e in doc.get("events", []))}


def run_baseline(port: int, seconds: float, realtime: bool) -> dict[str, Any]:
    """``ucom remote run`` for ``seconds``: the loop's figures without the gateway."""
    proc = subprocess.run(ucom("remote", "run", *connection(port, realtime), "--for",
                               f"{seconds:g}", "--json"), capture_output=True, text=True,
                          start_new_session=True, timeout=START_S + seconds + 60)
    try:
        return loop_figures(json.loads(proc.stdout), proc.stderr)
    except ValueError:
        raise SystemExit(f"remote run failed ({proc.returncode}): {proc.stderr[-2000:]}"
                         ) from None


def bus_plan(count: int = len(BUSES)) -> list[dict[str, Any]]:
    """Per CANopen bus (those of the first ``count`` UCoM buses): its channel, its joints'
    node IDs, the SO object each one's SDO uploads read besides 0x6064, and their
    dictionaries (for ``pdo_load``)."""
    robot = joints.load("armar3")
    plan = []
    for n, bus in enumerate(BUSES[:count]):
        mine = [j for j in robot.joints if j.bus == bus]
        ods = [dictionary.to_canopen(dictionary.build(j)) for j in mine]
        so = [min((i for i in od if 0x4000 <= i < 0x6000), default=0x6064) for od in ods]
        plan.append({"bus": bus, "channel": f"CO{n}", "nodes": [j.node_id for j in mine],
                     "so": so, "ods": ods})
    return plan


def master_line(proc: subprocess.Popen[str], gw: subprocess.Popen[str],
                deadline: float) -> str:
    """The line a master prints once measured; '' at once where the gateway ended first
    (it failed at its start: the master would wait :data:`START_S` for its nodes in
    vain) or the master ended, or at ``deadline``."""
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.2)
        if ready:
            return proc.stdout.readline()
        if gw.poll() is not None or proc.poll() is not None:
            return ""
    return ""


def run_gateway(port: int, rate: float, seconds: float, plan: list[dict[str, Any]],
                realtime: bool) -> dict[str, Any]:
    """The gateway for ``seconds`` + :data:`SETUP_S` with a master per CANopen bus."""
    specs = [f"{b['bus']}=socketcand:{b['channel']}@127.0.0.1:{port}" for b in plan]
    if len(plan) < len(BUSES):  # the other joints' nodes on a bus no master drives
        specs.append(f"socketcand:CO{len(plan)}@127.0.0.1:{port}")
    args = [a for s in specs for a in ("--canopen", s)]
    gw = subprocess.Popen(ucom("gateway", "canopen", *connection(port, realtime), *args,
                               "--for", f"{seconds + SETUP_S:g}", "--json"), text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          start_new_session=True)
    masters = []
    try:
        for b in plan:
            spec = MasterSpec("127.0.0.1", port, b["channel"], b["nodes"], b["so"], rate,
                              seconds, START_S)
            masters.append(subprocess.Popen(
                [sys.executable, __file__, "--master", json.dumps(asdict(spec))],
                text=True, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                stderr=subprocess.PIPE))  # in this session: Linux shares the processors
            # between sessions first; the masters stand for one other computer
        results = []
        deadline = time.monotonic() + START_S + seconds + SETUP_S + 60
        for proc in masters:  # each prints its figures once measured, then syncs on
            line = master_line(proc, gw, deadline)
            results.append(json.loads(line) if line.startswith("{") else
                           {"error": line + (proc.stderr.read()[-2000:]
                                             if proc.poll() is not None and proc.stderr
                                             else "")})
        out, err = gw.communicate(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        for proc in masters:
            with contextlib.suppress(OSError):
                assert proc.stdin is not None
                proc.stdin.close()  # the end: the master stops its SYNC and ends
        for proc in masters:
            stop(proc)
        stop(gw)
    try:
        doc = json.loads(out)
    except ValueError:
        raise SystemExit(f"gateway canopen failed ({gw.returncode}): {err[-2000:]}"
                         ) from None
    return {"loop": loop_figures(doc, err), "gateway": doc.get("gateway") or {},
            "masters": results}


def rate_figures(rate: float, got: dict[str, Any], base: dict[str, Any],
                 plan: list[dict[str, Any]]) -> dict[str, Any]:
    """One rate's figures (see the module docstring) from its run and its baseline."""
    masters = got["masters"]
    errors = [m["error"] for m in masters if "error" in m] + [
        f"{what}: {run['error']}" for what, run in (("remote run", base),
                                                    ("gateway canopen", got["loop"]))
        if run["error"]]
    ok = [m for m in masters if "error" not in m]
    lat = [x for m in ok for x in m["sync_tpdo_s"]]
    arrival = [x for m in ok for x in m["sync_tpdo_arrival_s"]]
    sdo = [x for m in ok for x in m["sdo_s"]]
    syncs = sum(m["syncs"] for m in ok)
    buses = got["gateway"].get("buses", [])
    joint_syncs = sum(b["syncs"] * len(b["nodes"]) for b in buses)
    loop = got["loop"]
    p99, base_p99 = loop["p99_ms"], base["p99_ms"]
    loads = {}
    for m, b in zip(ok, plan, strict=False):
        per_sync = m["bits_per_sync"]
        loads[b["channel"]] = {
            "bits_per_sync": per_sync,
            "load_pct": round(per_sync["counted"] * rate / BITRATE * 100, 1),
            "load_nominal_pct": round(per_sync["nominal"] * rate / BITRATE * 100, 1),
            "load_worst_pct": round(per_sync["worst"] * rate / BITRATE * 100, 1),
            "configured_worst_pct": round(pdo_load(b["ods"], rate).worst_bits_per_s
                                          / BITRATE * 100, 1)}

    def ms(values: list[float], p: float) -> float | None:
        return round(percentile(values, p) * 1e3, 3) if values else None

    return {
        "rate_hz": rate, "syncs": syncs,
        "complete_pct": round(100 * sum(m["complete"] for m in ok) / max(1, syncs), 2),
        "sync_tpdo_p50_ms": ms(lat, 50), "sync_tpdo_p99_ms": ms(lat, 99),
        "sync_tpdo_max_ms": round(max(lat) * 1e3, 3) if lat else None,
        "sync_tpdo_arrival_p50_ms": ms(arrival, 50),
        "sync_tpdo_arrival_p99_ms": ms(arrival, 99),
        "sdo_uploads": len(sdo), "sdo_p50_ms": ms(sdo, 50), "sdo_p99_ms": ms(sdo, 99),
        "sdo_max_ms": round(max(sdo) * 1e3, 3) if sdo else None,
        "sdo_timeouts": sum(m["sdo_timeouts"] for m in ok),
        "cpu_us_per_joint_sync": round(sum(b["sync_cpu_s"] for b in buses)
                                       / max(1, joint_syncs) * 1e6, 2),
        "thread_cpu_us_per_joint_sync": round(sum(b["thread_cpu_s"] for b in buses)
                                              / max(1, joint_syncs) * 1e6, 2) or None,
        "lateness_p99_ms": p99, "missed": loop["missed"],
        "watchdog_stops": loop["watchdog_stops"],
        "baseline_p99_ms": base_p99, "baseline_missed": base["missed"],
        "baseline_watchdog_stops": base["watchdog_stops"],
        "lateness_ratio": round(p99 / base_p99, 2) if p99 is not None and base_p99
        else None,
        "enabled": sum(m["enabled"] for m in ok),
        "joints": sum(len(b["nodes"]) for b in plan),
        "emcys": sum(m["emcys"] for m in ok), "buses": loads, "errors": errors,
        "writes_applied": got["gateway"].get("writes_applied"),
        "writes_refused": got["gateway"].get("writes_refused"),
        "last_refused": got["gateway"].get("last_refused"),
    }


def targets_of(figures: dict[str, Any]) -> dict[str, bool]:
    out = {}
    for r in figures["rates"]:
        hz = f"{r['rate_hz']:g} Hz"
        out[f"{hz}: SYNC to the last TPDO p99 <= 2 ms"] = \
            r["sync_tpdo_p99_ms"] is not None and r["sync_tpdo_p99_ms"] <= 2.0
        out[f"{hz}: SDO upload p99 <= 5 ms"] = \
            r["sdo_p99_ms"] is not None and r["sdo_p99_ms"] <= 5.0 and not r["sdo_timeouts"]
        out[f"{hz}: loop lateness p99 <= 1.2x without the gateway"] = \
            r["lateness_ratio"] is not None and r["lateness_ratio"] <= 1.2
        out[f"{hz}: every joint enabled, >= 99 % of the SYNCs complete"] = \
            r["enabled"] == r["joints"] and r["complete_pct"] >= 99.0 and not r["errors"]
        out[f"{hz}: no watchdog stop with the gateway (in its first run)"] = \
            r["attempts"] == 1 and not r["watchdog_stops"]
    return out


def report(figures: dict[str, Any], targets: dict[str, bool]) -> None:
    print(f"ARMAR-III's {figures['joints']} joints on {figures['canopen_buses']} CANopen "
          f"bus(es) beside the 1 kHz "
          f"loop over fleet serve, {figures['seconds']:g} s measured at each SYNC rate; "
          f"{figures['cores']} cores; run time {figures['run_time']}:")
    for r in figures["rates"]:
        print(f"  {r['rate_hz']:g} Hz SYNC: SYNC to the last TPDO p50 "
              f"{r['sync_tpdo_p50_ms']} ms, p99 {r['sync_tpdo_p99_ms']} ms, max "
              f"{r['sync_tpdo_max_ms']} ms (at the master's receiving thread p50 "
              f"{r['sync_tpdo_arrival_p50_ms']} / p99 {r['sync_tpdo_arrival_p99_ms']} ms); "
              f"{r['complete_pct']} % of {r['syncs']} SYNCs complete")
        print(f"    SDO upload p50 {r['sdo_p50_ms']} ms, p99 {r['sdo_p99_ms']} ms, max "
              f"{r['sdo_max_ms']} ms ({r['sdo_uploads']} uploads, {r['sdo_timeouts']} "
              f"timeouts); gateway CPU {r['cpu_us_per_joint_sync']} us per joint and SYNC "
              f"({r['thread_cpu_us_per_joint_sync']} us with its threads' idle turns)")
        print(f"    loop lateness p99 {r['lateness_p99_ms']} ms with the gateway, "
              f"{r['baseline_p99_ms']} ms without: {r['lateness_ratio']}x; missed "
              f"{r['missed']} / {r['baseline_missed']} cycles; watchdog stops "
              f"{r['watchdog_stops']} / {r['baseline_watchdog_stops']}; {r['enabled']} of "
              f"{r['joints']} joints enabled, {r['emcys']} EMCYs; runs "
              f"{r['attempts']}; the gateway's writes "
              f"{r['writes_applied']} applied, {r['writes_refused']} refused")
        for channel, b in r["buses"].items():
            print(f"    {channel}: {b['bits_per_sync']['frames']} frames, "
                  f"{b['bits_per_sync']['counted']} bits a SYNC: load {b['load_pct']} % "
                  f"(nominal {b['load_nominal_pct']} %, worst-case stuffing "
                  f"{b['load_worst_pct']} %; configured PDOs at most "
                  f"{b['configured_worst_pct']} %)")
        for e in r["errors"]:
            print(f"    failed: {e.strip()[-600:]}")
    print(f"  load average {figures['load_average']}")
    for name, ok in targets.items():
        print(f"  target {name}: {'MET' if ok else 'NOT MET'}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0,
                    help="measured at each SYNC rate (default 10)")
    ap.add_argument("--rates", default=",".join(f"{r:g}" for r in RATES),
                    help="SYNC rates in Hz (default 100,250)")
    ap.add_argument("--quick", action="store_true", help="3 s at each rate")
    ap.add_argument("--realtime", action="store_true",
                    help="the loop under SCHED_FIFO (remote run --realtime), both runs")
    ap.add_argument("--buses", type=int, default=len(BUSES), choices=range(1, len(BUSES) + 1),
                    help="CANopen buses (and masters): those of the first N UCoM buses' "
                    "joints (default 4, every joint)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    seconds = 3.0 if args.quick else args.seconds
    rates = [float(r) for r in args.rates.split(",")]
    plan = bus_plan(args.buses)
    per_rate = []
    with served() as port:
        for rate in rates:  # each against the baseline run just before it
            base = run_baseline(port, seconds + SETUP_S, args.realtime)
            attempts = 0
            while True:
                attempts += 1
                got = run_gateway(port, rate, seconds, plan, args.realtime)
                if not got["loop"]["watchdog_stops"] or attempts == ATTEMPTS:
                    break
            per_rate.append({**rate_figures(rate, got, base, plan), "attempts": attempts})
            if not args.json:
                print(f"  ({rate:g} Hz measured)", flush=True)
    figures: dict[str, Any] = {
        "seconds": seconds, "joints": sum(len(b["nodes"]) for b in plan),
        "canopen_buses": len(plan),
        "cores": os.cpu_count(), "realtime": args.realtime,
        "run_time": compiled.status().reason, "rates": per_rate,
        "load_average": round(os.getloadavg()[0], 2)}
    targets = targets_of(figures)
    figures["targets_met"] = targets
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        report(figures, targets)
    return 0 if all(targets.values()) else 1


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--master":  # a master (run_gateway)
        sys.exit(Master(MasterSpec(**json.loads(sys.argv[2]))).main())
    with stop_signals():
        sys.exit(main())
