"""``ucom dbc -o FILE``: the UCoM frames as a DBC database (:mod:`ucom_tools.trace.dbc`)."""

from __future__ import annotations

import sys
from pathlib import Path

import click
from rich.markup import escape

from ucom_tools.cli.output import stderr
from ucom_tools.trace import dbc as dbc_ops

HELP = """Export the UCoM frames as a DBC file for SavvyCAN, cantools monitor, CANalyzer
and other DBC tools.

One DBC message per identifier: the board number is in the identifier (bits 4-0, type
bit 5), not in the payload, so a DBC multiplexer cannot select it; each function has a
message per board that can send or receive it, named by function and board:
Info_3 (0x143, seq ID 3), Info_F5 (fixed ID 5), SetStatus_All (broadcast),
InitAck_Unnumbered, McaReady_2, SoMap_4 (process-data map 4).  The signals follow the
byte layouts of ucom-protocol(7); payloads whose layout depends on a field use plain
DBC multiplexing: Program Finished (kind), Info (frame index), Ready (reason), MCA
Admin Data (op).  Enumerated fields carry value tables (error codes, states, ops).

A frame is never decoded as something it is not: the database describes only what a
decoder can tell from the frame alone.  Each message has the length of its longest
form, which strict decoding (cantools decode) takes; a shorter form is left undecoded
there, and where truncated frames are allowed (cantools monitor, SavvyCAN,
decode_message(..., allow_truncated=True)) it shows the signals that fit, which are
right for it.  Identifiers 0x2C0-0x2FF (Program_Slot0-63) describe the data frame (DLC
8: four program words, one 64-bit signal, at the slot in bits 5-0): its first byte is
any value, so nothing in the payload tells it from a control frame (DLC 1-7, [0] op),
which is left undecoded ('ucom decode' reads both).  MCA Controller Input, Parameter
and DSP CI show their values as raw bytes (an edge's width, 2 or 4, its sign and scale
are in its MCA DumpIO Descr record).  SO and CI maps are raw messages of four masked
words: what they carry depends on the Admin Data SO_MAP/CI_MAP frames at run time, and
every byte travels XOR 0x55.

The file is written atomically; an existing one only with --force (else exit code 3).
-o - writes to standard output.  Needs cantools: pip install 'ucom-tools[dbc]'."""


@click.command("dbc", help=HELP)
@click.option("-o", "--output", required=True, metavar="FILE",
              help="The DBC file to write ('-': standard output).")
@click.option("--force", is_flag=True, help="Replace an existing FILE.")
def dbc(output: str, force: bool) -> None:
    if output == "-":
        sys.stdout.write(dbc_ops.dumps().replace("\r\n", "\n"))
        sys.stdout.flush()
        return
    count = dbc_ops.write(Path(output), force=force)
    stderr().print(f"wrote {escape(output)}: {count} messages", highlight=False)
