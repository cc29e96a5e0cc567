#!/usr/bin/env python3
"""Write the Intel HEX corpus of tests/data/ihex/ deterministically.

Good files:

- ``small.S``: a small image in the CodeWarrior convention (reset vector, 32 program words
  at P:0080, the descriptor of an ARMAR-III program at P:7DE0, 8 words of data flash at
  X:1000); ``small.hex``: it, written by ``ucom image convert`` (start linear address
  record first, 16 bytes a record);
- ``armar3.hex``: firmware_images/armar3.fl.S, written by ``ucom image convert``;
- ``legacy_objcopy.hex``: firmware_images/legacy_nodesc.fl.S as another toolchain writes
  it: its addresses doubled into a byte-addressed S-record file, put through
  ``objcopy -I srec -O ihex`` (CR LF line ends, a start segment address record 03);

and broken ones, each ``small.hex`` with one defect (see BROKEN below), and
``word_addressed_objcopy.hex``: ``small.S`` put through ``objcopy -I srec -O ihex`` as it
is, whose records overlap as bytes.

The files made with objcopy are only rewritten where objcopy is installed.
Usage: tools/make_ihex_corpus.py [OUTDIR]   (default tests/data/ihex)
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import bincopy

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from ucom_tools.image import formats  # noqa: E402
from ucom_tools.image.formats import load_image  # noqa: E402
from ucom_tools.image.model import runs  # noqa: E402
from ucom_tools.image.srec import parse_srec  # noqa: E402
from ucom_tools.wire.codes import Space  # noqa: E402
from ucom_tools.wire.descriptor import DESCRIPTOR_ADDRESS, ImageDescriptor  # noqa: E402

X_OFFSET = 0x0020_0000


def srec_record(address: int, words: list[int]) -> str:
    data = b"".join(w.to_bytes(2, "little") for w in words)
    return bincopy.pack_srec("3", address, len(data), data)


def small_srec() -> str:
    code = [(0x1111 * i + 0x0123) & 0xFFFF for i in range(32)]
    desc = ImageDescriptor(1, 1, 1, 0, (1, 0), "small test").to_words()
    data = [0xA000 + i for i in range(8)]
    lines = [bincopy.pack_srec("0", 0, 12, b"PROGRAM&DATA"), srec_record(0, [0xE984, 0x0080]),
             srec_record(0x80, code[:16]), srec_record(0x90, code[16:]),
             srec_record(DESCRIPTOR_ADDRESS, desc[:16]),
             srec_record(DESCRIPTOR_ADDRESS + 16, desc[16:]),
             srec_record(X_OFFSET + 0x1000, data), bincopy.pack_srec("7", 0x80, 0, None)]
    return "\n".join(lines) + "\n"


def ihex_record(address: int, kind: int, data: bytes, *, length: int | None = None) -> str:
    """A record with a correct checksum (``length``: a length byte that lies)."""
    raw = bytes([len(data) if length is None else length, address >> 8, address & 0xFF,
                 kind]) + data
    return ":" + (raw + bytes([-sum(raw) & 0xFF])).hex().upper()


def with_line(lines: list[str], index: int, new: str | None, *, insert: bool = False) -> str:
    out = list(lines)
    if insert:
        out.insert(index, new or "")
    elif new is None:
        del out[index]
    else:
        out[index] = new
    return "\n".join(out) + "\n"


def bad_checksum(line: str) -> str:
    return line[:-2] + ("00" if line[-2:] != "00" else "01")


def broken(good: list[str]) -> dict[str, str]:
    """name -> text: ``good`` (the lines of small.hex) with one defect each."""
    data = good[2]  # the first data record (after the start and the 04 record)
    assert data.startswith(":04000000"), data  # the reset vector at byte 0
    code = good[3]  # 16 bytes at 0x0100 (P:0080)
    assert code.startswith(":10010000"), code
    code_bytes = bytes.fromhex(code[9:-2])
    return {
        "bad_checksum.hex": with_line(good, 3, bad_checksum(code)),
        "unknown_type.hex": with_line(good, 4, ihex_record(0, 6, b"\x00\x00"), insert=True),
        "wrong_length.hex": with_line(good, 3, ihex_record(0x0100, 0, code_bytes,
                                                           length=0x0E)),
        "no_colon.hex": with_line(good, 3, code[1:]),
        "overlap.hex": with_line(good, 5, ihex_record(0x0108, 0, code_bytes[:8]),
                                 insert=True),
        "outside_regions.hex": with_line(good, 5, ihex_record(0xFC00, 0, b"\x01\x00"),
                                         insert=True),  # P:7E00, program RAM
        "no_eof.hex": with_line(good, len(good) - 1, None),
        "empty.hex": "",
        "lone_byte.hex": with_line(good, 5, ihex_record(0x0140, 0, b"\x01"), insert=True),
        "no_start.hex": with_line(good, 0, None),
        "after_eof.hex": with_line(good, len(good), ihex_record(0x0140, 0, b"\x01\x00"),
                                   insert=True),
        "srecords_named_hex.hex": small_srec(),
    }


def objcopy(source: Path, target: Path) -> None:
    subprocess.run(["objcopy", "-I", "srec", "-O", "ihex", str(source), str(target)],
                   check=True)


def byte_addressed(text: str) -> str:
    """An S-record image's text with its addresses doubled (bytes, not words)."""
    img = parse_srec(text)
    every = dict(img.words)
    every.update({(Space.P, a): v for a, v in img.vector_words.items()})
    lines = [bincopy.pack_srec("0", 0, 12, b"PROGRAM&DATA")]
    for space, start, values in runs(every):
        base = X_OFFSET if space is Space.X else 0
        for i in range(0, len(values), 16):
            data = b"".join(w.to_bytes(2, "little") for w in values[i:i + 16])
            lines.append(bincopy.pack_srec("3", 2 * (base + start + i), len(data), data))
    lines.append(bincopy.pack_srec("7", 2 * img.entry, 0, None))
    return "\n".join(lines) + "\n"


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    small = small_srec()
    (out / "small.S").write_text(small)
    small_hex = formats.dumps(parse_srec(small, "small.S"), "ihex")
    (out / "small.hex").write_text(small_hex)
    armar3 = load_image(ROOT / "firmware_images" / "armar3.fl.S")
    (out / "armar3.hex").write_text(formats.dumps(armar3, "ihex"))
    for name, text in broken(small_hex.splitlines()).items():
        (out / name).write_text(text)
    if shutil.which("objcopy") is None:
        print("objcopy not found: legacy_objcopy.hex and word_addressed_objcopy.hex kept")
        return
    with tempfile.TemporaryDirectory() as tmp:
        legacy = Path(tmp) / "legacy_bytes.S"
        legacy.write_text(byte_addressed(
            (ROOT / "firmware_images" / "legacy_nodesc.fl.S").read_text()))
        objcopy(legacy, out / "legacy_objcopy.hex")
    objcopy(out / "small.S", out / "word_addressed_objcopy.hex")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "tests" / "data" / "ihex")
