#!/usr/bin/env python3
"""Whole-robot ARMAR-III flashes over a served fleet that loses frames.

Each run starts ``ucom fleet serve armar3 --loss SHARE --seed S`` in another process (one
process per bus, fresh boards, on 127.0.0.1 and a free port) and flashes
``armar3.fl.S`` into all 11 boards over socketcand as ``ucom flash`` does (listen for
another host, reset, init chain, pre-flight, ProgEnable, the transfer with its rounds,
verification, Info read-back), all four buses in parallel.  The baseline, measured in the
same run: the same flash over the same kind of server without loss (median of
``--base-runs``).

Prints per seed the boards verified, the rounds and the data frames sent again on each
bus and the wall time; then the share of the runs in which all 11 boards verified and
the median wall time against the baseline's.  Target: 20 of 20 seeds verified (MET /
NOT MET).  ``--seeds N`` runs seeds 1..N only (default 20); ``--loss`` sets the share
lost each way (default 0.05).  ``--json`` prints the figures as JSON (keys: loss, seeds,
verified_runs, verified_share, base_wall_s, wall_s_median, wall_ratio, rounds_max,
resent_frames_median, target_met, runs: [{seed, verified_boards, rounds, resent_frames,
wall_s, failures}]).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import selectors
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ucom_tools.image.formats import load_image  # noqa: E402
from ucom_tools.ops.flash import flash, listen_first  # noqa: E402
from ucom_tools.ops.flash_types import FlashRequest  # noqa: E402
from ucom_tools.ops.robot import ConnectSpec, open_robot  # noqa: E402
from ucom_tools.signals import stop_signals  # noqa: E402

IMAGE = ROOT / "firmware_images" / "armar3.fl.S"
BOARDS = 11
START_S = 60.0
"""The longest a server may take to say where it listens (four processes, a busy machine)."""
STOP_S = 10.0


@contextlib.contextmanager
def served(loss: float, seed: int) -> Iterator[int]:
    """``ucom fleet serve armar3`` in a process group of its own; its port."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ucom_tools", "fleet", "serve", "armar3", "--host",
         "127.0.0.1", "--port", "0", "--loss", repr(loss), "--seed", str(seed)],
        text=True, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        start_new_session=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        assert proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            if not sel.select(timeout=START_S):
                raise SystemExit("fleet serve did not start")
        line = proc.stdout.readline()
        if not line.startswith("listening on"):
            raise SystemExit(f"fleet serve did not start: {line!r}")
        yield int(line.rsplit(":", 1)[1])
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(STOP_S)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(STOP_S)


def run(loss: float, seed: int, image: Any) -> dict[str, Any]:
    """One whole-robot flash over a served fleet losing ``loss`` each way."""
    with served(loss, seed) as port:
        robot = open_robot(ConnectSpec("socketcand", host="127.0.0.1", port=port,
                                       topology="armar3"))
        try:
            t0 = time.perf_counter()
            listen_first(robot)
            for h in robot.buses.values():
                h.client.reset()
            result = flash(robot, FlashRequest(image))
            wall = time.perf_counter() - t0
        finally:
            robot.close()
    verified = sum(b.verified for b in result.boards)
    return {"seed": seed, "verified_boards": verified,
            "verified": verified == BOARDS and result.all_verified,
            "rounds": {b.bus: b.rounds for b in result.buses},
            "resent_frames": sum(b.resent_frames for b in result.buses),
            "wall_s": round(wall, 3),
            "failures": [f"{b.bus}:{b.seq_id} {b.detail}" for b in result.boards
                         if not b.verified]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="seeds 1..N (default 20)")
    ap.add_argument("--loss", type=float, default=0.05, help="share lost each way")
    ap.add_argument("--base-runs", type=int, default=3, help="loss-free runs (median)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args()
    image = load_image(IMAGE)
    base = [run(0.0, seed, image) for seed in range(1, args.base_runs + 1)]
    if not all(b["verified"] for b in base):
        raise SystemExit(f"the loss-free baseline did not verify: {base}")
    base_wall = statistics.median(b["wall_s"] for b in base)
    runs = []
    for seed in range(1, args.seeds + 1):
        r = run(args.loss, seed, image)
        runs.append(r)
        if not args.json:
            rounds = " ".join(f"{bus} {n}" for bus, n in r["rounds"].items())
            print(f"seed {seed:>2}: {r['verified_boards']:>2} of {BOARDS} verified, rounds "
                  f"{rounds}, {r['resent_frames']:>4} frames sent again, {r['wall_s']:.2f} s"
                  + "".join(f"\n         {f}" for f in r["failures"]), flush=True)
    ok = sum(r["verified"] for r in runs)
    wall = statistics.median(r["wall_s"] for r in runs)
    met = ok == len(runs)
    figures = {"loss": args.loss, "seeds": len(runs), "verified_runs": ok,
               "verified_share": round(ok / len(runs), 4), "base_wall_s": base_wall,
               "wall_s_median": wall, "wall_ratio": round(wall / base_wall, 3),
               "rounds_max": max(max(r["rounds"].values()) for r in runs),
               "resent_frames_median": statistics.median(r["resent_frames"] for r in runs),
               "target_met": met, "runs": runs}
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        print(f"{IMAGE.name} ({image.size()} words) into all {BOARDS} ARMAR-III boards over "
              f"'ucom fleet serve armar3 --loss {args.loss:g}' (socketcand on 127.0.0.1, "
              "4 buses in parallel)")
        walls = ", ".join(f"{b['wall_s']:.2f}" for b in base)
        print(f"baseline, no loss: median {base_wall:.2f} s over {len(base)} runs ({walls})")
        print(f"{args.loss:.0%} loss each way: {ok} of {len(runs)} seeds verified all "
              f"{BOARDS} boards ({ok / len(runs):.0%}), median {wall:.2f} s = "
              f"{wall / base_wall:.2f}x the baseline, at most {figures['rounds_max']} rounds "
              f"on a bus, median {figures['resent_frames_median']:.0f} frames sent again")
        print(f"target: {len(runs)} of {len(runs)} verified: {'MET' if met else 'NOT MET'}")
    return 0 if met else 1


if __name__ == "__main__":
    with stop_signals():  # SIGTERM and SIGHUP as Ctrl-C: a served fleet is stopped too
        sys.exit(main())
