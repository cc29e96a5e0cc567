"""S-record images: the CodeWarrior convention, and a corpus of broken files that are
rejected with file, line and reason before anything reaches a bus."""

from __future__ import annotations

import json
from pathlib import Path

import bincopy
import pytest
from click.testing import CliRunner

from ucom_tools.cli.main import cli
from ucom_tools.errors import ImageError
from ucom_tools.image.formats import load_image
from ucom_tools.image.srec import parse_srec
from ucom_tools.wire.codes import Space

X = 0x0020_0000
HEADER = bincopy.pack_srec("0", 0, 12, b"PROGRAM&DATA")
END = bincopy.pack_srec("7", 0x80, 0, None)


def rec(address: int, words: list[int], kind: str = "3") -> str:
    data = b"".join(w.to_bytes(2, "little") for w in words)
    return bincopy.pack_srec(kind, address, len(data), data)


def good_lines() -> list[str]:
    return [HEADER, rec(0, [0xE984, 0x0080]), rec(0x80, [1, 2, 3, 4]), rec(0x84, [5, 6]),
            rec(X + 0x1000, [0xAAAA, 0xBBBB]), END]


def test_codewarrior_convention() -> None:
    img = parse_srec("\n".join(good_lines()), "ok.S")
    assert img.header == "PROGRAM&DATA"
    assert img.entry == 0x80
    assert img.addressing == "word"
    assert img.words[(Space.P, 0x80)] == 1 and img.words[(Space.P, 0x85)] == 6
    assert img.words[(Space.X, 0x1001)] == 0xBBBB
    assert img.vector_words == {0: 0xE984, 1: 0x0080}  # kept aside, not programmed
    assert [str(s) for s in img.segments()] == ["P:0080-0085", "X:1000-1001"]


def test_low_byte_first() -> None:
    img = parse_srec("\n".join([rec(0x80, [0xE984]), END]), "x.S")
    assert img.words[(Space.P, 0x80)] == 0xE984
    line = rec(0x80, [0xE984])
    assert "84E9" in line  # bytes 84 E9 = word 0xE984


def test_plain_s1_and_s2_files_and_byte_addressing() -> None:
    s1 = "\n".join([rec(0x80, [1, 2], "1"), rec(0x82, [3], "1"),
                    bincopy.pack_srec("9", 0x80, 0, None)])
    assert parse_srec(s1).entry == 0x80
    s2 = "\n".join([rec(0x80, [1, 2], "2"), bincopy.pack_srec("8", 0x80, 0, None)])
    assert parse_srec(s2).size() == 2
    byte_addressed = "\n".join([rec(0x100, [1, 2, 3, 4], "1"), rec(0x108, [5, 6], "1"),
                                rec(0x10C, [7], "1"), bincopy.pack_srec("9", 0x100, 0, None)])
    img = parse_srec(byte_addressed)
    assert img.addressing == "byte"
    assert sorted(a for _, a in img.words) == list(range(0x80, 0x87))


def test_bundled_images_fit_flash_and_are_reproducible(tmp_path: Path) -> None:
    import subprocess
    import sys
    subprocess.run([sys.executable, "tools/make_firmware_images.py", str(tmp_path)],
                   check=True)
    for path in sorted(Path("firmware_images").glob("*.S")):
        assert (tmp_path / path.name).read_bytes() == path.read_bytes(), path.name
        img = load_image(path)
        assert img.size() <= 32252 + 3840
    assert load_image("firmware_images/bench64k.fl.S").size() * 2 == 64 * 1024


def _with(lines: list[str], index: int, new: str | None) -> str:
    out = list(lines)
    if new is None:
        del out[index]
    else:
        out[index] = new
    return "\n".join(out) + "\n"


def _bad_checksum() -> str:
    line = rec(0x80, [1, 2, 3, 4])
    return line[:-2] + ("00" if line[-2:] != "00" else "01")


CORPUS = [
    ("bad_checksum", _with(good_lines(), 2, _bad_checksum()), 3, "checksum"),
    ("not_hex", _with(good_lines(), 3, "S3090000008405XX0600E7"), 4, "malformed"),
    ("short_record", _with(good_lines(), 3, "S3090000"), 4, "record cut short"),
    ("type_s4", _with(good_lines(), 3, "S4030000FC"), 4, "unknown record type S4"),
    ("not_srecord", "this is not an S-record file\n", 1, "not an S-record"),
    ("odd_bytes", _with(good_lines(), 3, bincopy.pack_srec("3", 0x84, 3, b"\x01\x02\x03")),
     4, "odd number of data bytes"),
    ("overlap", _with(good_lines(), 3, rec(0x83, [9, 9])), 4, "also written on line 3"),
    ("boot_flash", _with(good_lines(), 3, rec(0x8000, [1])), 4, "boot flash"),
    ("program_ram", _with(good_lines(), 3, rec(0x7E00, [1])), 4, "program RAM"),
    ("peripherals", _with(good_lines(), 4, rec(X + 0x0C00, [1])), 5, "peripheral"),
    ("boot_record", _with(good_lines(), 4, rec(X + 0x1F00, [1])), 5, "bootloader record"),
    ("external_ram", _with(good_lines(), 4, rec(X + 0x2000, [1])), 5, "external memory"),
    ("unmapped_p", _with(good_lines(), 3, rec(0x9000, [1])), 4, "unmapped"),
    ("beyond_16_bit", _with(good_lines(), 3, rec(0x10000, [1])), 4, "outside the 16-bit"),
    ("count_mismatch", _with(good_lines(), 5, bincopy.pack_srec("5", 7, 0, None)) + END,
     6, "count record says 7"),
    ("after_end", "\n".join([*good_lines(), rec(0x90, [1])]) + "\n", 7, "after the termination"),
    ("entry_outside", _with(good_lines(), 5, bincopy.pack_srec("7", 0x8000, 0, None)), 6,
     "entry address"),
    ("empty", "\n\n", None, "empty file"),
    ("only_vectors", "\n".join([HEADER, rec(0, [0xE984, 0x80]), END]) + "\n", None,
     "only reset-vector words"),
]


@pytest.mark.parametrize("name, text, line, reason", CORPUS, ids=[c[0] for c in CORPUS])
def test_broken_files_are_rejected_with_line_and_reason(tmp_path: Path, name: str, text: str,
                                                        line: int | None, reason: str) -> None:
    path = tmp_path / f"{name}.S"
    path.write_text(text)
    with pytest.raises(ImageError) as info:
        load_image(path)
    assert info.value.file == str(path)
    assert info.value.line == line
    assert reason in info.value.reason


@pytest.mark.parametrize("name, text, line, reason", CORPUS[:6] + CORPUS[7:9],
                         ids=[c[0] for c in CORPUS[:6] + CORPUS[7:9]])
def test_flash_refuses_broken_files_before_touching_a_bus(tmp_path: Path, name: str, text: str,
                                                          line: int | None,
                                                          reason: str) -> None:
    path = tmp_path / f"{name}.S"
    path.write_text(text)
    state = tmp_path / "fleet-state"
    r = CliRunner().invoke(cli, ["flash", str(path), "--virtual", "armar3", "--state",
                                 str(state)])
    assert r.exit_code == 3
    assert f"{path}:{line}:" in r.stderr and reason in r.stderr
    assert not state.exists()  # the fleet was never opened: no frame was sent


def test_binary_and_missing_files(tmp_path: Path) -> None:
    blob = tmp_path / "fw.bin"
    blob.write_bytes(b"S3\xff\xfe\x00")
    with pytest.raises(ImageError, match="non-ASCII"):
        load_image(blob)
    with pytest.raises(ImageError, match="no such file"):
        load_image(tmp_path / "nope.S")
    with pytest.raises(ImageError, match="directory"):
        load_image(tmp_path)


def test_srec_info_and_progid_commands() -> None:
    r = CliRunner().invoke(cli, ["srec", "info", "firmware_images/armar3.fl.S", "--json"])
    assert r.exit_code == 0
    data = json.loads(r.stdout)
    img = load_image("firmware_images/armar3.fl.S")
    assert data["progid"] == f"0x{img.progid:08X}"
    assert data["entry"] == "P:0080"
    assert data["words"] == {"P": img.size(Space.P), "X": img.size(Space.X)}
    assert [s["space"] for s in data["segments"]] == ["P", "P", "X"]  # code, descriptor, data
    assert data["descriptor"] == {"board_id": 1, "board": "3M", "app_id": 1,
                                  "application": "ARMAR-III cascaded velocity/position PID, "
                                                 "3 axes", "fpga_version": "1.0",
                                  "program_version": "3.2", "name": "armar3 cascaded PID"}
    assert data["flags"] == []
    r = CliRunner().invoke(cli, ["srec", "info", "firmware_images/legacy_nodesc.fl.S", "--json"])
    assert json.loads(r.stdout)["descriptor"] is None
    assert "no image descriptor" in json.loads(r.stdout)["flags"][0]
    r = CliRunner().invoke(cli, ["srec", "progid", "firmware_images/armar3.fl.S"])
    assert r.stdout.strip() == f"0x{img.progid:08X}"
    r = CliRunner().invoke(cli, ["srec", "info", "firmware_images/armar3.fl.S"])
    assert "ProgID" in r.stdout and "P:0080" in r.stdout
