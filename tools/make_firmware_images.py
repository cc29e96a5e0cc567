#!/usr/bin/env python3
"""Write the sample images of firmware_images/ deterministically.

Each image follows the Metrowerks CodeWarrior 56800 S-record convention: an S0 header
"PROGRAM&DATA", S3 data records whose addresses are WORD addresses (X: data at
0x00200000 + word address), every 16-bit word stored low byte first, and an S7 entry.
The reset vector P:0000-0001 is a JMP to the entry, as CodeWarrior writes it (the
bootloader keeps its own vectors; see man/ucom-protocol.7).

The contents are pseudo-random but fixed by the image name: the same file comes out
every time.  Usage: tools/make_firmware_images.py [OUTDIR]
"""

from __future__ import annotations

import hashlib
import random
import sys
from pathlib import Path

import bincopy

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from ucom_tools.wire.descriptor import DESCRIPTOR_ADDRESS, ImageDescriptor

X_OFFSET = 0x0020_0000
WORDS_PER_RECORD = 16

DESCRIPTOR_WORDS = 32

# name: (entry, program words, data-flash words, descriptor or None)
#   descriptor: (Board-ID, App-ID, FPGA major, FPGA minor, version, program name)
IMAGES = {
    "armar3.fl.S": (0x0080, 11_520, 768, (1, 1, 1, 0, (3, 2), "armar3 cascaded PID")),
    "lauron4.fl.S": (0x0080, 9_216, 512, (1, 2, 1, 0, (2, 0), "lauron4 leg")),
    "kairo2_alpha.fl.S": (0x0080, 7_680, 256, (7, 1, 1, 0, (1, 4), "kairo2 alpha drive")),
    "kairo2_gamma.fl.S": (0x0080, 8_704, 384, (8, 1, 1, 0, (1, 4), "kairo2 gamma joint")),
    "rosi.fl.S": (0x0080, 4_096, 128, (1, 3, 1, 0, (1, 0), "rosi rotation")),
    # Odete and Puma200 had no image of their own (ucom deploy's manifests name these)
    "odete_drive.fl.S": (0x0080, 3_072, 128, (5, 1, 1, 0, (1, 0), "odete drive")),
    "odete_odometry.fl.S": (0x0080, 2_048, 128, (4, 1, 1, 0, (1, 0), "odete odometry")),
    "puma200.fl.S": (0x0080, 6_144, 256, (1, 4, 1, 0, (1, 0), "puma200 joint")),
    "puma200_brakes.fl.S": (0x0080, 2_048, 64, (3, 1, 1, 0, (1, 0), "puma200 brakes")),
    # built for a newer FPGA minor version: runs with a warning
    "armar3_fpga1.1.fl.S": (0x0080, 11_520, 768, (1, 1, 1, 1, (3, 3), "armar3 cascaded PID")),
    # built for FPGA 2.x: refused before programming, aborted at start
    "armar3_fpga2.fl.S": (0x0080, 11_520, 768, (1, 1, 2, 0, (4, 0), "armar3 cascaded PID")),
    # an old image from before descriptors: programmable, flagged
    "legacy_nodesc.fl.S": (0x0080, 2_048, 0, None),
    # 64 KiB in all (descriptor included) for the benchmarks
    "bench64k.fl.S": (0x0080, 32_768 - 3_840 - DESCRIPTOR_WORDS, 3_840,
                      (1, 1, 1, 0, (0, 1), "64 KiB benchmark")),
}


def words_for(name: str, count: int, salt: str) -> list[int]:
    seed = int.from_bytes(hashlib.sha256(f"{name}/{salt}".encode()).digest()[:8], "big")
    rnd = random.Random(seed)
    return [rnd.getrandbits(16) for _ in range(count)]


def records(space_base: int, start: int, words: list[int]) -> list[str]:
    out = []
    for i in range(0, len(words), WORDS_PER_RECORD):
        chunk = words[i:i + WORDS_PER_RECORD]
        data = b"".join(w.to_bytes(2, "little") for w in chunk)
        out.append(bincopy.pack_srec("3", space_base + start + i, len(data), data))
    return out


def image_text(name: str, entry: int, p_words: int, x_words: int,
               descriptor: tuple | None) -> str:
    lines = [bincopy.pack_srec("0", 0, 12, b"PROGRAM&DATA")]
    lines += records(0, 0, [0xE984, entry])  # reset vector: JMP entry
    lines += records(0, entry, words_for(name, min(p_words, DESCRIPTOR_ADDRESS - entry), "P"))
    if descriptor is not None:
        board_id, app_id, major, minor, version, program = descriptor
        desc = ImageDescriptor(board_id, app_id, major, minor, version, program)
        lines += records(0, DESCRIPTOR_ADDRESS, desc.to_words())
    if x_words:
        lines += records(X_OFFSET, 0x1000, words_for(name, x_words, "X"))
    lines.append(bincopy.pack_srec("7", entry, 0, None))
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    out = Path(argv[1]) if len(argv) > 1 else Path(__file__).resolve().parent.parent / \
        "firmware_images"
    out.mkdir(parents=True, exist_ok=True)
    for name, (entry, p, x, desc) in IMAGES.items():
        (out / name).write_text(image_text(name, entry, p, x, desc), encoding="ascii")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
