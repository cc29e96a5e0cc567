#!/usr/bin/env python3
"""``ucom deploy`` of ARMAR-III on the in-process fleet (virtual time), against a baseline
measured in the same run: ``ucom flash`` of the whole robot (reset, init chain, every
board programmed, verified and read back), as a robot was brought up before deploy.

Figures (each the fastest of ``--repeat`` runs, default 3):

- ``flash_s``: the baseline, flash of armar3.fl.S into all 11 boards;
- ``flash_keep_params_s``: the same with ``--keep-params`` (every board's values read
  before, loaded back after), what keeping the values took before deploy;
- ``up_to_date_s``: deploy of the robot that matches its manifest (plan only: init chain
  and Info per bus, nothing sent to any board);
- ``one_board_s``: deploy where one board's image differs (the neck gets
  armar3_fpga1.1.fl.S, then armar3.fl.S again, alternately): its parameters dumped,
  one board programmed, parameters loaded back, started;
- ``init_s``: ``ucom init`` (init chain, Info, probe on every bus), for the goal that
  an up-to-date deploy take at most 2x of it;
- per figure the virtual bus time too (``*_virtual_s``: the fleet clock, buses one after
  the other as virtual time runs them) and the ratios ``flash_s / up_to_date_s``,
  ``flash_s / one_board_s``, ``up_to_date_s / init_s``.

``--json`` prints the figures as one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ucom_tools.config import topology as topo_mod  # noqa: E402
from ucom_tools.image.formats import load_image  # noqa: E402
from ucom_tools.ops import deploy as ops  # noqa: E402
from ucom_tools.ops import params_keep  # noqa: E402
from ucom_tools.ops.deploy_execute import execute  # noqa: E402
from ucom_tools.ops.enumerate import enumerate_bus  # noqa: E402
from ucom_tools.ops.flash import flash  # noqa: E402
from ucom_tools.ops.flash_types import FlashRequest  # noqa: E402
from ucom_tools.ops.robot import ConnectSpec, Robot, open_robot  # noqa: E402
from ucom_tools.virtual.canbus import VirtualUcomBus  # noqa: E402

IMAGES = ROOT / "firmware_images"


def changed_manifest(directory: Path) -> Path:
    text = (ROOT / "ucom_tools/config/topologies/armar3.toml").read_text()
    text = text.replace('tree = "attribute_trees/', f'tree = "{ROOT}/attribute_trees/')
    text = text.replace('image = "firmware_images/', f'image = "{IMAGES}/')
    first = text.index("armar3.fl.S")  # the neck, the first board
    text = text[:first] + "armar3_fpga1.1.fl.S" + text[first + len("armar3.fl.S"):]
    path = directory / "armar3-neck.toml"
    path.write_text(text)
    return path


def clock(r: Robot) -> float:
    h = next(iter(r.buses.values()))
    assert isinstance(h.bus, VirtualUcomBus)
    return h.bus.fleet.now_us() / 1e6


def timed(r: Robot, work: Callable[[], object], repeat: int) -> tuple[float, float]:
    """(fastest wall seconds, its virtual seconds)."""
    best = (float("inf"), 0.0)
    for _ in range(repeat):
        v0, t0 = clock(r), time.perf_counter()
        work()
        wall, virtual = time.perf_counter() - t0, clock(r) - v0
        best = min(best, (wall, virtual))
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure (the fastest)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="ucom-bench-deploy-") as tmp:
        directory = Path(tmp)
        plain = ops.load_manifest(topo_mod.load("armar3"))
        neck = ops.load_manifest(topo_mod.load(str(changed_manifest(directory))))
        image = load_image(IMAGES / "armar3.fl.S")
        r = open_robot(ConnectSpec(virtual="armar3", state_dir=directory / "state"))
        try:
            def deploy(manifest: ops.Manifest, changes: int) -> None:
                journal = ops.Journal.open(directory / "journal", "ARMAR-III")
                request = ops.DeployRequest(manifest, journal)
                result = execute(r, request, ops.plan(r, request))
                assert result.ok and len(result.plan.changes) == changes, result.failed

            deploy(plain, 11)  # every board gets its program first
            flash_s, flash_v = timed(r, lambda: (
                [h.client.reset() for h in r.buses.values()],
                flash(r, FlashRequest(image))), args.repeat)
            deploy(plain, 11)  # flash left the boards in their bootloader: start them

            def flash_keep() -> None:
                kept = params_keep.keep_before(r)
                for h in r.buses.values():
                    h.client.reset()
                result = flash(r, FlashRequest(image, start=True))
                restored = params_keep.keep_after(r, kept, {(b.bus, b.seq_id): b.outcome
                                                           for b in result.boards})
                assert result.all_verified and restored.ok

            keep_s, keep_v = timed(r, flash_keep, args.repeat)
            deploy(plain, 11)  # AutoStart again
            init_s, init_v = timed(r, lambda: r.each(enumerate_bus), args.repeat)
            up_s, up_v = timed(r, lambda: deploy(plain, 0), args.repeat)
            state = {"manifest": plain}

            def one_board() -> None:
                state["manifest"] = neck if state["manifest"] is plain else plain
                deploy(state["manifest"], 1)

            one_s, one_v = timed(r, one_board, args.repeat)
        finally:
            r.close()
    figures = {
        "flash_s": round(flash_s, 3), "flash_virtual_s": round(flash_v, 3),
        "flash_keep_params_s": round(keep_s, 3), "flash_keep_params_virtual_s": round(keep_v, 3),
        "up_to_date_s": round(up_s, 3), "up_to_date_virtual_s": round(up_v, 3),
        "one_board_s": round(one_s, 3), "one_board_virtual_s": round(one_v, 3),
        "init_s": round(init_s, 3), "init_virtual_s": round(init_v, 3),
        "flash_over_up_to_date": round(flash_s / up_s, 1),
        "flash_over_one_board": round(flash_s / one_s, 1),
        "flash_keep_params_over_one_board": round(keep_s / one_s, 1),
        "up_to_date_over_init": round(up_s / init_s, 2),
    }
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        print("ARMAR-III, 11 boards on 4 buses, in-process fleet (virtual time); "
              f"fastest of {args.repeat}")
        print(f"baseline  flash of the whole robot:        {flash_s:7.3f} s wall "
              f"({flash_v:.3f} s virtual)")
        print(f"baseline  flash --keep-params, whole robot: {keep_s:7.3f} s wall "
              f"({keep_v:.3f} s virtual)")
        print(f"deploy    robot up to date:                {up_s:7.3f} s wall "
              f"({up_v:.3f} s virtual)  flash/deploy = {flash_s / up_s:.1f}x")
        print(f"deploy    one board differs (neck):        {one_s:7.3f} s wall "
              f"({one_v:.3f} s virtual)  flash/deploy = {flash_s / one_s:.1f}x, "
              f"flash --keep-params/deploy = {keep_s / one_s:.1f}x")
        print(f"init      chain + Info on every bus:       {init_s:7.3f} s wall "
              f"({init_v:.3f} s virtual)")
        print(f"goal      up-to-date deploy <= 2x init:    {up_s / init_s:.2f}x "
              f"{'MET' if up_s <= 2 * init_s else 'NOT MET'}")
    return 0 if up_s <= 2 * init_s else 1


if __name__ == "__main__":
    sys.exit(main())
