"""Intel HEX images: read with the same strictness as S-records (FILE:LINE, exit code 3,
nothing sent), programmed with the ProgID of the S-record they came from, and converted
both ways without loss (tests/data/ihex/, written by tools/make_ihex_corpus.py)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import intelhex
import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli
from ucom_tools.errors import ImageError
from ucom_tools.image import formats, ihex
from ucom_tools.image.formats import load_image
from ucom_tools.image.srec import parse_srec
from ucom_tools.wire.codes import Space

ROOT = Path(__file__).resolve().parent.parent
CORPUS = ROOT / "tests" / "data" / "ihex"
FIRMWARE = ROOT / "firmware_images"


def ucom(*args: str, input: str | None = None) -> Result:
    return CliRunner().invoke(cli, list(args), input=input)


def snapshot(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


BROKEN = [  # (file, line, what the message must say)
    ("bad_checksum.hex", 4, "checksum mismatch: the record ends in 00, its bytes give 17"),
    ("unknown_type.hex", 5, "unknown record type 06"),
    ("wrong_length.hex", 4, "wrong record length: its length byte 0E promises 14 data bytes, "
                            "38 hex digits after ':', the line has 42"),
    ("no_colon.hex", 4, "the line does not begin with ':'"),
    ("overlap.hex", 6, "byte 0x108 (word P:0084) is also written on line 4 (overlapping "
                       "data)"),
    ("outside_regions.hex", 6, "word P:7E00 lies in program RAM; only program flash "
                               "P:0004-7DFF and data flash X:1000-1EFF can be programmed"),
    ("no_eof.hex", 13, "no end-of-file record (:00000001FF): the file ends after line 13; "
                       "is it truncated?"),
    ("empty.hex", None, "empty file: no Intel HEX records"),
    ("word_addressed_objcopy.hex", 4, "is also written on line 3 (overlapping data); a "
                                      "word-addressed S-record file (CodeWarrior) put "
                                      "through objcopy -O ihex"),
    ("lone_byte.hex", 6, "byte 0x140 has no partner at 0x141: word P:00A0 needs both"),
    ("no_start.hex", 13, "no start address record"),
    ("after_eof.hex", 15, "record after the end-of-file record of line 14"),
    ("srecords_named_hex.hex", 1, "this line is an S-record (ucom reads a file named .hex"),
]
IDS = [b[0].removesuffix(".hex") for b in BROKEN]


# ----------------------------------------------------------------------- broken files
@pytest.mark.parametrize("name, line, reason", BROKEN, ids=IDS)
def test_each_broken_file_is_refused_with_file_line_and_defect(name: str, line: int | None,
                                                               reason: str) -> None:
    path = CORPUS / name
    with pytest.raises(ImageError) as info:
        load_image(path)
    assert info.value.file == str(path)
    assert info.value.line == line
    assert reason in info.value.reason


def test_intelhex_itself_accepts_what_we_refuse_as_truncated() -> None:
    """Why the end-of-file record is checked here: the package takes a file without one,
    and an empty file, for an image."""
    assert len(intelhex.IntelHex(str(CORPUS / "no_eof.hex"))) > 0
    assert len(intelhex.IntelHex(str(CORPUS / "empty.hex"))) == 0
    with pytest.raises(intelhex.AddressOverlapError):  # and refuses this one as we do
        intelhex.IntelHex(str(CORPUS / "word_addressed_objcopy.hex"))


@pytest.mark.parametrize("name, line, reason", BROKEN, ids=IDS)
def test_flash_of_a_broken_file_is_exit_3_and_touches_no_board(
        tmp_path: Path, name: str, line: int | None, reason: str) -> None:
    path = tmp_path / name
    shutil.copyfile(CORPUS / name, path)
    state = tmp_path / "fleet-state"
    r = ucom("flash", str(path), "--virtual", "armar3", "--state", str(state))
    assert r.exit_code == 3, r.stderr
    where = f"{path}:{line}: " if line is not None else f"{path}: "
    assert where in r.stderr and reason in " ".join(r.stderr.split())
    assert "Traceback" not in r.stderr
    assert not state.exists()  # the fleet was never opened: no frame was sent


def test_a_broken_file_leaves_programmed_boards_as_they_were(tmp_path: Path) -> None:
    state = tmp_path / "fleet-state"
    r = ucom("flash", str(CORPUS / "small.hex"), "--virtual", "armar3", "--state", str(state),
             "--bus", "CAN0")
    assert r.exit_code == 0, r.stdout + r.stderr
    before = snapshot(state)
    assert before
    for name in ("overlap.hex", "no_eof.hex", "bad_checksum.hex"):
        for command in (["flash", str(CORPUS / name)],
                        ["program", "all", str(CORPUS / name), "--init"],
                        ["extram-load", "1", str(CORPUS / name), "--init"]):
            r = ucom(*command, "--virtual", "armar3", "--state", str(state))
            assert r.exit_code == 3, (command, r.stderr)
            assert snapshot(state) == before, command


# ------------------------------------------------------------------------- good files
@pytest.mark.parametrize("hex_name, srec", [
    ("armar3.hex", FIRMWARE / "armar3.fl.S"),
    ("small.hex", CORPUS / "small.S"),
    ("legacy_objcopy.hex", FIRMWARE / "legacy_nodesc.fl.S"),
])
def test_good_files_flash_and_verify_with_the_progid_of_their_s_record(
        tmp_path: Path, hex_name: str, srec: Path) -> None:
    progid = f"0x{load_image(srec).progid:08X}"
    r = ucom("flash", str(CORPUS / hex_name), "--virtual", "armar3", "--json")
    assert r.exit_code == 0, r.stdout + r.stderr
    result = json.loads(r.stdout)
    assert result["progid"] == progid and result["all_verified"]
    assert len(result["boards"]) == 11
    assert {b["verified_progid"] for b in result["boards"]} == {progid}


def test_another_toolchains_file_reads_as_its_s_record() -> None:
    """objcopy's output of a byte-addressed S-record: CR LF, 16 bytes a record, the entry
    as a start segment address record (03, CS:IP = 0000:0100)."""
    path = CORPUS / "legacy_objcopy.hex"
    assert b"\r\n" in path.read_bytes() and ":0400000300000100F8" in path.read_text()
    img, ref = load_image(path), load_image(FIRMWARE / "legacy_nodesc.fl.S")
    assert (img.format, img.addressing) == ("ihex", "byte")
    assert img.words == ref.words and img.vector_words == ref.vector_words
    assert img.entry == ref.entry == 0x80


def record(address: int, kind: int, data: bytes) -> str:
    raw = bytes([len(data), address >> 8, address & 0xFF, kind]) + data
    return ":" + (raw + bytes([-sum(raw) & 0xFF])).hex().upper()


def test_byte_addresses_map_to_p_and_x_words_low_byte_first() -> None:
    lines = [
        record(0, 5, (0x100).to_bytes(4, "big")),  # start linear address 2 x entry P:0080
        record(0, 0, bytes.fromhex("84E98000")),  # P:0000-0001 at bytes 0-3: reset vector
        record(0x100, 0, bytes.fromhex("3412")),  # P:0080 = 0x1234 at bytes 0x100-0x101
        record(0, 4, bytes.fromhex("0040")),  # extended linear address: 0x0040xxxx
        record(0x2000, 0, bytes.fromhex("CDAB")),  # X:1000 = 0xABCD at 0x00402000
        ":00000001FF"]
    assert lines[0] == ":0400000500000100F6" and lines[3] == ":020000040040BA"
    img = ihex.parse_ihex("\n".join(lines), "x.hex")
    assert img.entry == 0x80
    assert img.words == {(Space.P, 0x80): 0x1234, (Space.X, 0x1000): 0xABCD}
    assert img.vector_words == {0: 0xE984, 1: 0x0080}
    split = [*lines[:2], record(0x100, 0, b"\x34"), record(0x101, 0, b"\x12"), *lines[3:]]
    assert ihex.parse_ihex("\n".join(split)).words == img.words  # a word in two records
    segment = [record(0, 3, bytes.fromhex("00100000")), *lines[1:]]  # CS:IP = 0010:0000
    assert ihex.parse_ihex("\n".join(segment)).entry == 0x80
    odd = [record(0, 5, (0x101).to_bytes(4, "big")), *lines[1:]]
    with pytest.raises(ImageError, match="start address 0x101 is odd") as info:
        ihex.parse_ihex("\n".join(odd), "odd.hex")
    assert info.value.line == 1


def test_the_format_is_chosen_by_extension_then_by_content(tmp_path: Path) -> None:
    text = (CORPUS / "small.hex").read_text()
    for name in ("fw.hex", "FW.IHEX", "fw.ihx", "fw.txt", "fw"):
        (tmp_path / name).write_text("\n\n  " + text if name in ("fw.txt", "fw") else text)
        assert load_image(tmp_path / name).format == "ihex", name
    (tmp_path / "fw.S").write_text((CORPUS / "small.S").read_text())
    assert load_image(tmp_path / "fw.S").format == "srec"
    (tmp_path / "odd.S").write_text(text)  # content decides where the name does not
    assert load_image(tmp_path / "odd.S").format == "ihex"
    with pytest.raises(ImageError, match="word addressing is for S-record files"):
        load_image(tmp_path / "fw.hex", addressing="word")
    (tmp_path / "dir.hex").mkdir()
    with pytest.raises(ImageError, match="is a directory, not an Intel HEX file"):
        load_image(tmp_path / "dir.hex")


def test_size_cap_and_binary_data_as_for_s_records(tmp_path: Path) -> None:
    big = tmp_path / "big.hex"
    big.write_text(":0400000500000100F6\n")
    with big.open("r+b") as f:
        f.truncate(17 * 1024 * 1024)  # sparse: a line, then NUL bytes
    with pytest.raises(ImageError) as info:
        load_image(big)
    assert info.value.reason == ("file is larger than 16 MiB; not an Intel HEX image for a "
                                 "DSP56F803")
    blob = tmp_path / "fw.hex"
    blob.write_bytes(b":04000005\x00\x01\n")
    with pytest.raises(ImageError) as info:
        load_image(blob)
    assert (info.value.line, info.value.column) == (1, 10)
    assert info.value.reason == "not an Intel HEX file: NUL byte (binary data)"


# ------------------------------------------------------------------------- conversion
@pytest.mark.parametrize("srec", sorted(FIRMWARE.glob("*.S")), ids=lambda p: p.name)
def test_round_trip_srec_hex_srec_is_identical(tmp_path: Path, srec: Path) -> None:
    original = load_image(srec)
    hex_text = formats.dumps(original, "ihex")
    via_hex = ihex.parse_ihex(hex_text, "x.hex")
    back_text = formats.dumps(via_hex, "srec")
    back = parse_srec(back_text, "x.S")
    for img in (via_hex, back):
        assert img.words == original.words and img.vector_words == original.vector_words
        assert img.entry == original.entry and img.progid == original.progid
    assert back_text == srec.read_text()  # byte for byte: the CodeWarrior convention
    ih = intelhex.IntelHex()  # the package reads what we write as it is
    path = tmp_path / "x.hex"
    path.write_text(hex_text)
    ih.loadhex(str(path))
    assert ih.start_addr == {"EIP": 2 * original.entry}
    every = {**{(Space.P, a): v for a, v in original.vector_words.items()}, **original.words}
    assert len(ih) == 2 * len(every)
    for (space, addr), value in every.items():
        b = 2 * addr + (0x0040_0000 if space is Space.X else 0)
        assert ih[b] | (ih[b + 1] << 8) == value


def test_image_convert_command_both_ways(tmp_path: Path) -> None:
    hex_path, srec_path = tmp_path / "a.hex", tmp_path / "a.S"
    r = ucom("image", "convert", str(FIRMWARE / "armar3.fl.S"), str(hex_path))
    assert r.exit_code == 0, r.stderr
    assert "wrote" in r.stderr and "Intel HEX" in r.stderr
    assert hex_path.read_text() == (CORPUS / "armar3.hex").read_text()
    r = ucom("image", "convert", str(hex_path), str(srec_path))
    assert r.exit_code == 0, r.stderr
    assert srec_path.read_bytes() == (FIRMWARE / "armar3.fl.S").read_bytes()
    r = ucom("image", "convert", str(CORPUS / "small.S"), "-")  # standard output: HEX
    assert r.exit_code == 0 and r.stdout == (CORPUS / "small.hex").read_text()
    r = ucom("image", "convert", str(CORPUS / "small.hex"), "-", "--to", "ihex")
    assert r.stdout == (CORPUS / "small.hex").read_text()


def test_convert_replaces_an_existing_out_only_with_force(tmp_path: Path) -> None:
    out = tmp_path / "out.hex"
    out.write_text("keep me\n")
    r = ucom("image", "convert", str(CORPUS / "small.S"), str(out))
    assert r.exit_code == 3 and "exists; --force replaces it" in r.stderr
    assert out.read_text() == "keep me\n"
    r = ucom("image", "convert", str(CORPUS / "small.S"), str(out), "--force")
    assert r.exit_code == 0 and out.read_text() == (CORPUS / "small.hex").read_text()
    r = ucom("image", "convert", str(CORPUS / "small.S"), str(tmp_path / "x.hex"), "--to",
             "srec")
    assert r.exit_code == 3 and "read as Intel HEX" in r.stderr
    assert not (tmp_path / "x.hex").exists()
    r = ucom("image", "convert", str(CORPUS / "overlap.hex"), str(tmp_path / "y.S"))
    assert r.exit_code == 3 and f"{CORPUS / 'overlap.hex'}:6:" in r.stderr
    assert not (tmp_path / "y.S").exists()
    r = ucom("image", "convert", str(CORPUS / "small.S"), str(tmp_path / "no" / "z.hex"))
    assert r.exit_code == 3 and "does not exist" in r.stderr
    assert list(tmp_path.iterdir()) == [out]  # no temporary file left


# -------------------------------------------------------------------------- commands
def test_image_info_shows_either_format_and_srec_info_is_an_alias() -> None:
    srec_info = json.loads(ucom("image", "info", str(FIRMWARE / "armar3.fl.S"),
                                "--json").stdout)
    hex_info = json.loads(ucom("image", "info", str(CORPUS / "armar3.hex"), "--json").stdout)
    alias = json.loads(ucom("srec", "info", str(CORPUS / "armar3.hex"), "--json").stdout)
    assert alias == hex_info
    assert (srec_info["format"], hex_info["format"]) == ("S-record", "Intel HEX")
    assert hex_info["addressing"] == "byte" and hex_info["header"] == ""
    for key in ("progid", "entry", "words", "segments", "vector_words", "descriptor", "blocks"):
        assert hex_info[key] == srec_info[key], key
    r = ucom("image", "progid", str(CORPUS / "armar3.hex"))
    assert r.stdout.strip() == srec_info["progid"]
    text = " ".join(ucom("image", "info", str(CORPUS / "armar3.hex")).stdout.split())
    assert "format Intel HEX (1545 records, byte addresses)" in text
    assert srec_info["progid"] in text and "P:0080" in text


def test_program_and_extram_load_take_hex(tmp_path: Path) -> None:
    rosi = tmp_path / "rosi.hex"
    assert ucom("image", "convert", str(FIRMWARE / "rosi.fl.S"), str(rosi)).exit_code == 0
    common = ["--virtual", "rosi", "--state", str(tmp_path / "state"), "--init", "--json"]
    progid = f"0x{load_image(FIRMWARE / 'rosi.fl.S').progid:08X}"
    r = ucom("program", "1", str(rosi), *common)
    assert r.exit_code == 0, r.stderr
    board = json.loads(r.stdout)["boards"][0]
    assert (board["outcome"], board["verified_progid"]) == ("verified", progid)
    r = ucom("extram-load", "1", str(rosi), *common)
    assert r.exit_code == 0 and json.loads(r.stdout)["target"] == "extram"


def test_console_option_18_loads_hex() -> None:
    progid = f"0x{load_image(FIRMWARE / 'armar3.fl.S').progid:08X}"
    r = ucom("console", "--virtual", "armar3",
             input=f"load {CORPUS / 'armar3.hex'}\n19\nload {CORPUS / 'no_eof.hex'}\nq\n")
    assert r.exit_code == 0, r.stdout + r.stderr
    out = " ".join(r.stdout.split())
    assert f"ProgID {progid}" in out and f"ProgID of armar3.hex: {progid}" in out
    assert "no_eof.hex:13: no end-of-file record" in out  # refused, the console goes on


def test_the_corpus_is_what_the_generator_writes(tmp_path: Path) -> None:
    subprocess.run([sys.executable, str(ROOT / "tools" / "make_ihex_corpus.py"),
                    str(tmp_path)], check=True, capture_output=True)
    for path in sorted(tmp_path.iterdir()):
        assert path.read_bytes() == (CORPUS / path.name).read_bytes(), path.name
    made = {p.name for p in tmp_path.iterdir()}
    objcopy = {"legacy_objcopy.hex", "word_addressed_objcopy.hex"}
    assert made | objcopy == {p.name for p in CORPUS.iterdir()}


CUTS = [  # (characters of the last data record kept, where it ends)
    (4, "inside the address"), (7, "inside the record type"), (20, "inside the data"),
    (40, "before the checksum"), (41, "inside the checksum")]


@pytest.mark.parametrize("keep, where", CUTS, ids=[c[1].replace(" ", "_") for c in CUTS])
def test_a_file_cut_inside_a_record_names_line_and_place(tmp_path: Path, keep: int,
                                                         where: str) -> None:
    lines = (CORPUS / "small.hex").read_text().splitlines()
    path = tmp_path / "cut.hex"
    path.write_text("\n".join([*lines[:3], lines[3][:1 + keep]]))
    with pytest.raises(ImageError) as info:
        load_image(path)
    assert info.value.line == 4
    assert info.value.reason.startswith("record cut short: its length byte 10 promises 16 "
                                        "data bytes, 42 hex digits after ':'")
    assert info.value.reason.endswith(f"the line has only {keep}; it ends {where}")


@pytest.mark.parametrize("byte_count", [7, 32, 255])
def test_hex_from_another_writer_with_any_record_size_reads_the_same(
        tmp_path: Path, byte_count: int) -> None:
    """intelhex's own writer, records of an odd size too (words split across records)."""
    ref = load_image(FIRMWARE / "armar3.fl.S")
    ih = intelhex.IntelHex()
    ih.loadhex(str(CORPUS / "armar3.hex"))
    path = tmp_path / "other.hex"
    with path.open("w") as f:
        ih.write_hex_file(f, byte_count=byte_count)
    img = load_image(path)
    assert (img.words, img.vector_words, img.entry, img.progid) == (
        ref.words, ref.vector_words, ref.entry, ref.progid)
