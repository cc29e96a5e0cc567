#!/usr/bin/env python3
"""Recording and viewing beside the loop (issue 36, part 3): the 1 kHz ARMAR-III loop over
``ucom fleet serve armar3`` with ``--record run.mcap --foxglove`` and a Foxglove client
subscribed to every channel, against the same run without, in the same benchmark run.

ARMAR-III (armar3.fl.S flashed) is served by ``fleet serve`` (a process per bus, a session
of its own, as in ``benchmarks/consumers.py``); ``ucom remote run armar3 -i socketcand
--for SECONDS --json`` runs first alone (the baseline), then with ``--record DIR/run.mcap
--foxglove 127.0.0.1:PORT``, a client no one here wrote (``@foxglove/ws-protocol`` under
node, ``benchmarks/foxglove_latency.cjs``, from the npm cache the tests install,
``tests/test_foxglove.py``) subscribed to every channel from the server's start.

Figures: ``lateness_p99_ms`` / ``baseline_p99_ms`` and their ``lateness_ratio`` (target
at most 1.2x); ``missed_pct`` / ``baseline_missed_pct`` (target at most the baseline +
0.1 point); ``cpu_us_per_frame``: the run's processes' CPU over the baseline's per frame
recorded, and ``cpu_us_per_value``: the same per value message the server encoded (a
rough split: both cost in the one consumers' process, so each figure charges all of it
to one kind); ``mcap_mb_per_min`` (the file's size per minute of ARMAR-III);
``delivery_p50_ms`` / ``delivery_p99_ms`` of the values channels (target p99 <= 20 ms at
100 Hz values) and of everything (``delivery_all_p99_ms``).  ``--json`` prints them;
without node and its client the delivery figures are null and say why.

Both runs are made twice (``--mode``, default both, in turn): with the loop's thread at
normal priority, as anyone runs it, and with ``--realtime`` (SCHED_FIFO), as a robot's PC
runs its 1 kHz loop; ``--json`` prints the figures of each under ``normal`` and
``realtime``.  On two cores the consumers' process, the node client and the served fleet
share the loop's processors: at normal priority the loop waits for them now and then,
with ``--realtime`` it does not, and they get what it leaves.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.consumers import served_armar3, ucom  # noqa: E402

CLIENT = ROOT / "benchmarks" / "foxglove_latency.cjs"
NODE_CACHE = "ucom-test-node-foxglove+ws-protocol0.8.0-ws8.23.1"
"""Where ``tests/test_foxglove.py`` installs the client's packages (the temporary
directory); the benchmark installs nothing itself."""


def node_modules() -> Path | None:
    cache = Path(tempfile.gettempdir()) / NODE_CACHE / "node_modules"
    return cache if (cache / "@foxglove" / "ws-protocol").is_dir() else None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run(port: int, seconds: float, extra: list[str]) -> tuple[dict[str, Any], float]:
    """``remote run`` over the served fleet; its --json and the CPU it used (with its
    consumers' process)."""
    cpu = children_cpu()
    done = subprocess.run(ucom("remote", "run", "armar3", "-i", "socketcand", "--host",
                               "127.0.0.1", "--port", str(port), "--for", str(seconds),
                               "--json", *extra), capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"remote run {' '.join(extra)} failed ({done.returncode}): "
                         f"{done.stderr[-2000:]}")
    return json.loads(done.stdout), children_cpu() - cpu


def until_listening(port: int, deadline: float) -> bool:
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port),
                                                                    timeout=0.2):
            return True
        time.sleep(0.05)  # a poll interval for another process's server
    return False


def measure(seconds: float, loop: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {"cores": os.cpu_count(), "seconds": seconds}
    modules = node_modules()
    node = shutil.which("node")
    with served_armar3() as port, tempfile.TemporaryDirectory() as tmp:
        base, base_cpu = run(port, seconds, loop)
        fox = free_port()
        mcap = Path(tmp) / "run.mcap"
        client = None
        if not (node and modules):
            out["delivery_why"] = ("node is not installed" if not node else
                                   "the Foxglove client's packages are not in the npm cache "
                                   "(run tests/test_foxglove.py once)")
        proc_cpu0 = children_cpu()
        runner = subprocess.Popen(
            ucom("remote", "run", "armar3", "-i", "socketcand", "--host", "127.0.0.1",
                 "--port", str(port), "--for", str(seconds), "--json", "--record",
                 str(mcap), "--foxglove", f"127.0.0.1:{fox}", *loop),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if node and modules:
            if until_listening(fox, time.monotonic() + 60):  # before the boards start
                client = subprocess.Popen(
                    [node, str(CLIENT), f"ws://127.0.0.1:{fox}", str(seconds + 60)],
                    stdout=subprocess.PIPE, text=True, start_new_session=True,
                    env={**os.environ, "NODE_PATH": str(modules)})
            else:
                out["delivery_why"] = "the Foxglove server did not listen within 60 s"
        stdout, stderr = runner.communicate()
        cpu = children_cpu() - proc_cpu0
        if runner.returncode:
            raise SystemExit(f"remote run --record --foxglove failed ({runner.returncode}): "
                             f"{stderr[-2000:]}")
        doc = json.loads(stdout)
        if client is not None:
            client.terminate()  # it prints its figures so far: the run has ended
            got, _ = client.communicate(timeout=30)
            lines = [ln for ln in got.splitlines() if ln.startswith("{")]
            lat = json.loads(lines[-1]) if lines else {}
            if not lines:
                out["delivery_why"] = f"the client printed no figures (exit {client.returncode})"
            values = [v for k, v in lat.items() if k.endswith("/values")]
            out["delivery_p50_ms"] = max((v["p50_ms"] for v in values if v["p50_ms"]),
                                         default=None)
            out["delivery_p99_ms"] = max((v["p99_ms"] for v in values if v["p99_ms"]),
                                         default=None)
            out["delivery_all_p99_ms"] = lat.get("all", {}).get("p99_ms")
            out["delivered"] = lat.get("all", {}).get("count")
        size = mcap.stat().st_size if mcap.exists() else 0
    cycles = doc["run"]["cycles"] or 1
    frames = sum((doc.get("record") or {}).get("frames", {}).values()) or 1
    fstats = doc.get("foxglove") or {}
    values = sum(v for k, v in (fstats.get("encoded") or {}).items()
                 if k.endswith("/values")) or 1
    extra_cpu = cpu - base_cpu
    out.update({
        "lateness_p99_ms": doc["run"]["jitter_ms"]["p99"],
        "baseline_p99_ms": base["run"]["jitter_ms"]["p99"],
        "missed_pct": round(100 * doc["run"]["missed"] / cycles, 3),
        "baseline_missed_pct": round(100 * base["run"]["missed"] / (base["run"]["cycles"]
                                                                    or 1), 3),
        "cpu_s": round(cpu, 3), "baseline_cpu_s": round(base_cpu, 3),
        "frames_recorded": frames, "values_encoded": values,
        "cpu_us_per_frame": round(extra_cpu / frames * 1e6, 2),
        "cpu_us_per_value": round(extra_cpu / values * 1e6, 2),
        "mcap_mb_per_min": round(size / 1e6 / seconds * 60, 1),
    })
    out["lateness_ratio"] = round(out["lateness_p99_ms"] / max(out["baseline_p99_ms"],
                                                               1e-6), 2)
    return out


def targets(f: dict[str, Any]) -> list[tuple[str, bool | None]]:
    p99 = f.get("delivery_p99_ms")
    return [("loop lateness p99 <= 1.2x without recording and viewer",
             f["lateness_ratio"] <= 1.2),
            ("missed <= the baseline's + 0.1 point",
             f["missed_pct"] <= f["baseline_missed_pct"] + 0.1),
            ("delivery p99 <= 20 ms (values)", None if p99 is None else p99 <= 20.0)]


MODES = {"normal": [], "realtime": ["--realtime"]}
"""How the loop's thread is scheduled, in both runs of a mode: at normal priority (any
user) and with ``remote run --realtime`` (SCHED_FIFO, as a robot's PC runs its 1 kHz
loop; it needs the privilege, and a refusal is reported by the run)."""


def say(mode: str, seconds: float, f: dict[str, Any], met: list[tuple[str, bool | None]]
        ) -> None:
    print(f"ARMAR-III at 1 kHz over fleet serve, {seconds:g} s, {f['cores']} cores, the loop "
          f"at {mode} priority: with --record run.mcap --foxglove and a client subscribed "
          f"to everything, lateness p99 {f['lateness_p99_ms']} ms against "
          f"{f['baseline_p99_ms']} ms without ({f['lateness_ratio']}x); missed "
          f"{f['missed_pct']} % against {f['baseline_missed_pct']} %")
    print(f"  CPU {f['cpu_s']} s against {f['baseline_cpu_s']} s: "
          f"{f['cpu_us_per_frame']} us per recorded frame ({f['frames_recorded']}), "
          f"{f['cpu_us_per_value']} us per published values message "
          f"({f['values_encoded']}); MCAP {f['mcap_mb_per_min']} MB a minute")
    if f.get("delivery_p99_ms") is not None:
        print(f"  delivery to the client: values p50 {f['delivery_p50_ms']} ms, p99 "
              f"{f['delivery_p99_ms']} ms; everything p99 {f['delivery_all_p99_ms']} ms "
              f"({f['delivered']} messages)")
    else:
        print(f"  delivery: not measured ({f.get('delivery_why', 'no figures')})")
    for name, ok in met:
        print(f"  target {name}: " + ("not measured" if ok is None else "MET" if ok
                                      else "NOT MET"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--mode", choices=[*MODES, "both"], default="both",
                    help="how the loop's thread is scheduled (default: both, in turn)")
    args = ap.parse_args()
    modes = list(MODES) if args.mode == "both" else [args.mode]
    out: dict[str, Any] = {}
    ok = True
    for mode in modes:
        f = measure(args.seconds, MODES[mode])
        met = targets(f)
        f["targets_met"] = {name: done for name, done in met}
        ok = ok and all(done is not False for _, done in met)
        out[mode] = f
        if not args.json:
            say(mode, args.seconds, f, met)
    if args.json:
        print(json.dumps(out))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
