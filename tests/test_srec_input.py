"""Bad S-record input is rejected clearly, early and without reading it all: truncated
files, devices and FIFOs, huge files, binary data - each with file, line and reason, never
a traceback or a hang, and never with a bus opened."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import bincopy
import pytest
from click.testing import CliRunner

from ucom_tools.cli.main import cli
from ucom_tools.errors import ImageError
from ucom_tools.image.formats import load_image
from ucom_tools.image.srec import parse_srec

X = 0x0020_0000
HEADER = bincopy.pack_srec("0", 0, 12, b"PROGRAM&DATA")
END = bincopy.pack_srec("7", 0x80, 0, None)
LAST = bincopy.pack_srec("3", 0x84, 4, b"\x05\x00\x06\x00")  # S309 00000084 05000600 CC
"""A data record: length byte at [2:4], address [4:12], data [12:20], checksum [20:22]."""


def rec(address: int, words: list[int]) -> str:
    data = b"".join(w.to_bytes(2, "little") for w in words)
    return bincopy.pack_srec("3", address, len(data), data)


def good_lines() -> list[str]:
    return [HEADER, rec(0, [0xE984, 0x0080]), rec(0x80, [1, 2, 3, 4]), LAST,
            rec(X + 0x1000, [0xAAAA, 0xBBBB]), END]


def write(path: Path, lines: list[str], *, newline: str = "\n") -> Path:
    path.write_bytes(newline.join(lines).encode("ascii") + newline.encode("ascii"))
    return path


def reject(path: Path) -> ImageError:
    with pytest.raises(ImageError) as info:
        load_image(path)
    assert info.value.file == str(path)
    return info.value


def bytes_read_by_this_process() -> int | None:
    """``rchar`` of /proc/self/io: every byte this process got from read(2), or None."""
    try:
        for line in Path("/proc/self/io").read_text().splitlines():
            if line.startswith("rchar:"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


# ------------------------------------------------------------------------ truncated files

def test_a_file_without_termination_record_is_refused_as_truncated(tmp_path: Path) -> None:
    lines = good_lines()[:-1]
    err = reject(write(tmp_path / "no_end.S", [*lines, "", ""]))  # blank lines do not count
    assert err.line == 5
    assert err.reason == ("no termination record (S7, S8 or S9): the file ends after line 5; "
                          "is it truncated?")
    with pytest.raises(ImageError, match="no termination record") as info:
        parse_srec("\n".join(lines), "text.S")
    assert info.value.line == 5


CUTS = [  # (where the last data record is cut, how many characters are left, the message)
    ("length_byte", 3, "the S3 record ends inside its length byte"),
    ("address", 9, "the line has only 5; it ends inside the address"),
    ("data", 16, "the line has only 12; it ends inside the data"),
    ("before_checksum", 20, "the line has only 16; it ends before the checksum"),
    ("checksum", 21, "the line has only 17; it ends inside the checksum"),
]


@pytest.mark.parametrize("newline", ["\n", ""], ids=["line_end", "no_line_end"])
@pytest.mark.parametrize("where, keep, message", CUTS, ids=[c[0] for c in CUTS])
def test_a_file_cut_inside_its_last_record_names_line_and_place(
        tmp_path: Path, where: str, keep: int, message: str, newline: str) -> None:
    lines = [*good_lines()[:3], LAST[:keep]]
    path = tmp_path / f"cut_{where}.S"
    path.write_text("\n".join(lines) + newline)
    err = reject(path)
    assert err.line == 4
    assert err.reason.startswith("record cut short: ")
    assert err.reason.endswith(message)
    if keep > 4:  # the length byte is there: what it promised is spelled out
        assert "its length byte 09 promises 9 bytes (4 address, 4 data, 1 checksum), " \
               "18 hex digits" in err.reason


def test_a_cut_record_in_the_middle_is_found_although_the_file_ends_properly(
        tmp_path: Path) -> None:
    lines = good_lines()
    lines[3] = LAST[:14]
    err = reject(write(tmp_path / "cut_middle.S", lines))
    assert err.line == 4
    assert err.reason == ("record cut short: its length byte 09 promises 9 bytes (4 address, "
                          "4 data, 1 checksum), 18 hex digits, the line has only 10; it ends "
                          "inside the data")


def test_a_cut_termination_record_is_named(tmp_path: Path) -> None:
    lines = good_lines()
    lines[-1] = END[:-1]
    err = reject(write(tmp_path / "cut_end.S", lines))
    assert err.line == 6
    assert err.reason == ("record cut short: its length byte 05 promises 5 bytes (4 address, "
                          "1 checksum), 10 hex digits, the line has only 9; it ends inside the "
                          "checksum")


def test_length_bytes_that_do_not_fit_the_line_or_the_type(tmp_path: Path) -> None:
    lines = good_lines()
    lines[3] = LAST + "00"  # two more digits than the length byte promises
    err = reject(write(tmp_path / "long.S", lines))
    assert (err.line, err.reason) == (4, "malformed record: its length byte 09 promises 9 "
                                         "bytes (4 address, 4 data, 1 checksum), 18 hex "
                                         "digits, the line has 20")
    # bincopy.unpack_srec takes this one, the checksum being right: address from the sum
    lines[3] = "S3" + bincopy.pack_srec("1", 0x12, 0, None)[2:]
    err = reject(write(tmp_path / "small.S", lines))
    assert (err.line, err.reason) == (4, "malformed record: length byte 03 is too small for "
                                         "an S3 record, whose 4 address bytes and checksum "
                                         "need 5")


# ------------------------------------------------------------ devices, huge files, streams

def test_dev_zero_is_refused_as_a_device_at_once() -> None:
    if not Path("/dev/zero").exists():
        pytest.skip("no /dev/zero")
    # In a child process with a time and memory bound: reading /dev/zero whole would hang
    # and eat all memory, and must fail this test, not the machine.
    child = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (2**30, 2**30)); "
             "from ucom_tools.cli.main import main; main()")
    started = time.monotonic()
    r = subprocess.run([sys.executable, "-c", child, "srec", "info", "/dev/zero"],
                       capture_output=True, text=True, timeout=10,
                       env={**os.environ, "COLUMNS": "200"})
    assert time.monotonic() - started < 10
    assert r.returncode == 3, r.stderr
    assert "/dev/zero: is a device, not a regular file" in r.stderr
    assert "Traceback" not in r.stderr


def _sparse(path: Path, first_line: str) -> Path:
    path.write_text(first_line + "\n")
    os.truncate(path, 2**30)  # 1 GiB: one line of text, then a hole of NUL bytes
    return path


def test_a_huge_file_that_is_no_s_record_file_is_refused_at_line_1_unread(
        tmp_path: Path) -> None:
    path = _sparse(tmp_path / "huge.log", "2024-05-01 12:00:00 robot started")
    before = bytes_read_by_this_process()
    started = time.monotonic()
    err = reject(path)
    assert time.monotonic() - started < 2
    assert (err.line, err.reason) == (1, "not an S-record: 2024-05-01 12:00:00 robot started")
    after = bytes_read_by_this_process()
    if before is not None and after is not None:
        assert after - before < 1024 * 1024  # a few KiB of buffer, not the gigabyte


def test_a_huge_file_that_starts_like_an_image_is_refused_by_its_size(
        tmp_path: Path) -> None:
    path = _sparse(tmp_path / "huge.S", HEADER)
    before = bytes_read_by_this_process()
    err = reject(path)
    assert err.line is None
    assert err.reason == "file is larger than 16 MiB; not an S-record image for a DSP56F803"
    after = bytes_read_by_this_process()
    if before is not None and after is not None:
        assert after - before < 1024 * 1024


def _image_larger_than(size: int) -> list[str]:
    """The lines of a valid image (header, data records, S7) of more than ``size`` bytes."""
    lines = [HEADER + "\n"]
    total, address = len(lines[0]), 0x80
    while total <= size:
        lines.append(rec(address, list(range(16))) + "\n")
        total += len(lines[-1])
        address += 16
    return [*lines, END + "\n"]


def test_a_fifo_is_refused_at_once_without_a_writer(tmp_path: Path) -> None:
    """A FIFO nobody writes to would block an open() for reading forever; it is looked
    at without blocking and refused (exit code 3), as every input that is not a regular
    file (ucom(1), FILES)."""
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs here")
    fifo = tmp_path / "image.S"
    os.mkfifo(fifo)
    r = subprocess.run([sys.executable, "-m", "ucom_tools", "srec", "info", str(fifo)],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 3, r.stderr
    assert f"{fifo}: is a FIFO, not a regular file" in r.stderr
    assert "Traceback" not in r.stderr


def test_the_size_limit_counts_every_byte_with_line_ends(
        monkeypatch: pytest.MonkeyPatch) -> None:
    text = "\r\n".join(good_lines()) + "\r\n"
    monkeypatch.setattr("ucom_tools.image.text.MAX_FILE_BYTES", len(text))
    assert parse_srec(text).size() == 8
    monkeypatch.setattr("ucom_tools.image.text.MAX_FILE_BYTES", len(text) - 1)
    with pytest.raises(ImageError, match="larger than") as info:
        parse_srec(text)
    assert info.value.line == 6


def test_overlong_lines_are_refused_at_their_line(tmp_path: Path) -> None:
    lines = good_lines()
    lines[2] = "S3" + "F" * 1000
    err = reject(write(tmp_path / "long_line.S", lines))
    assert (err.line, err.reason) == (3, "not an S-record: the line is longer than 578 "
                                         "characters (a record has at most 514)")
    longest = bincopy.pack_srec("1", 0x80, 252, bytes(252))  # length byte FF
    assert len(longest) == 2 + 2 * (1 + 255)
    img = parse_srec("\n".join([f"  {longest}\t", bincopy.pack_srec("9", 0x80, 0, None)]))
    assert img.size() == 126


# ------------------------------------------------------------------------ bytes and lines

def test_binary_bytes_are_refused_at_their_line_and_column(tmp_path: Path) -> None:
    good = "\n".join(good_lines()).encode("ascii")
    cases = [(b"\xe9", "non-ASCII byte 0xE9"), (b"\x00", "NUL byte (binary data)"),
             (b"\x1a", "control character 0x1A")]
    for byte, what in cases:
        lines = good.split(b"\n")
        lines[2] = lines[2][:10] + byte + lines[2][10:]
        path = tmp_path / "binary.S"
        path.write_bytes(b"\n".join(lines))
        err = reject(path)
        assert (err.line, err.column, err.reason) == (3, 11, f"not an S-record file: {what}")


def test_crlf_cr_blank_lines_and_blanks_around_records_are_accepted(tmp_path: Path) -> None:
    lines = good_lines()
    spaced = [lines[0], "", f"  {lines[1]}", f"{lines[2]} \t", "", *lines[3:], "", ""]
    for newline in ("\r\n", "\n", "\r"):
        img = load_image(write(tmp_path / "ok.S", spaced, newline=newline))
        assert (img.records, img.size(), img.entry) == (6, 8, 0x80)
    lines[3] = "S3" + lines[3][2:].lower()
    assert parse_srec("\n".join(lines)).size() == 8


def test_a_hex_digit_error_names_its_column(tmp_path: Path) -> None:
    lines = good_lines()
    lines[3] = "  " + LAST[:6] + "G" + LAST[7:]
    err = reject(write(tmp_path / "not_hex.S", lines))
    assert (err.line, err.column, err.reason) == (4, 9, "malformed record: 'G' is not a hex "
                                                        "digit")


def test_s6_count_records_are_read() -> None:
    s6 = "S6" + bincopy.pack_srec("2", 4, 0, None)[2:]  # 24-bit count, which bincopy lacks
    img = parse_srec("\n".join([*good_lines()[:-1], s6, END]))
    assert img.records == 7
    bad = "S6" + bincopy.pack_srec("2", 3, 0, None)[2:]
    with pytest.raises(ImageError, match="count record says 3 data records"):
        parse_srec("\n".join([*good_lines()[:-1], bad, END]))


def test_missing_directory_and_unreadable_files_keep_clear_errors(tmp_path: Path) -> None:
    assert reject(tmp_path / "nope.S").reason == "no such file"
    assert reject(tmp_path).reason == "is a directory, not an S-record file"
    if Path("/proc/self/mem").exists():  # opens, then read(2) fails with EIO
        with pytest.raises(ImageError) as info:
            load_image("/proc/self/mem")
        assert info.value.reason == "cannot read: Input/output error"
    if os.geteuid() != 0:  # root reads anything
        locked = write(tmp_path / "locked.S", good_lines())
        locked.chmod(0)
        try:
            assert reject(locked).reason == "cannot read: Permission denied"
        finally:
            locked.chmod(0o644)


# ------------------------------------------------------------------------------- the CLI

def _truncated_files(tmp_path: Path) -> list[tuple[Path, int, str]]:
    cut_last = [*good_lines()[:3], LAST[:16]]
    cut_middle = good_lines()
    cut_middle[2] = cut_middle[2][:20]
    (tmp_path / "cut_last.S").write_text("\n".join(cut_last))  # cut: no line end either
    return [
        (write(tmp_path / "no_end.S", good_lines()[:-1]), 5, "no termination record (S7, S8 "
                                                             "or S9): the file ends after "
                                                             "line 5; is it truncated?"),
        (tmp_path / "cut_last.S", 4, "record cut short: "),
        (write(tmp_path / "cut_middle.S", cut_middle), 3, "record cut short: "),
    ]


def test_srec_info_reports_truncation_as_bad_input(tmp_path: Path) -> None:
    for path, line, message in _truncated_files(tmp_path):
        r = CliRunner(env={"COLUMNS": "300"}).invoke(cli, ["srec", "info", str(path)])
        assert r.exit_code == 3, r.output
        err = " ".join(r.stderr.split())
        assert f"ucom: bad input: {path}:{line}: {message}" in err
        assert "Traceback" not in r.stderr and r.stdout == ""


def test_flash_refuses_a_truncated_file_before_opening_a_bus(tmp_path: Path) -> None:
    for path, line, message in _truncated_files(tmp_path):
        state = tmp_path / f"state-{path.stem}"
        r = CliRunner(env={"COLUMNS": "300"}).invoke(
            cli, ["flash", str(path), "--virtual", "rosi", "--state", str(state)])
        assert r.exit_code == 3, r.output
        assert f"{path}:{line}: {message}" in " ".join(r.stderr.split())
        assert "Traceback" not in r.stderr
        assert not state.exists()  # the fleet was never opened: no frame was sent
