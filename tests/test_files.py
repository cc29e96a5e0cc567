"""What ucom writes and reads, by the rules of ucom(1), FILES: devices, FIFOs and links are
never replaced, regular files are replaced whole or not at all with one mode rule, write
failures are one line and exit code 5, inputs are regular files of a bounded size.

Real files, real devices (``mknod`` under a temporary directory), real FIFOs and small
tmpfs mounts (root only: CI runs as root here; each test says why it skips elsewhere),
the real command as a user runs it (a subprocess where standard output matters)."""

from __future__ import annotations

import contextlib
import os
import stat
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from ucom_tools import fileio
from ucom_tools.cli.main import cli
from ucom_tools.errors import InputError, WriteError

ROOT = Path(__file__).resolve().parent.parent
EYES = ROOT / "attribute_trees" / "armar3" / "head_right.tree"
IMAGE = ROOT / "firmware_images" / "armar3.fl.S"


def ucom(*args: str) -> Result:
    return CliRunner().invoke(cli, list(args))


def run(*args: str, stdout: int | None = subprocess.PIPE, timeout: float = 120,
        **kwargs: object) -> subprocess.CompletedProcess[str]:
    """``ucom ARGS`` as its own process (the real entry point, with its stdout guard)."""
    return subprocess.run([sys.executable, "-m", "ucom_tools", *args], stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=timeout,
                          env={**os.environ, "COLUMNS": "200"}, **kwargs)  # type: ignore[call-overload]


def device(path: Path, major: int, minor: int) -> Path:
    """A character device node (1,3 is /dev/null, 1,7 /dev/full) or a skip saying why."""
    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(major, minor))
    except (PermissionError, OSError) as err:
        pytest.skip(f"cannot make a device node here ({err.strerror}); needs root")
    return path


def is_char_device(path: Path) -> bool:
    return stat.S_ISCHR(os.lstat(path).st_mode)


@contextlib.contextmanager
def tmpfs(where: Path, size: str = "256k", *, readonly: bool = False) -> Iterator[Path]:
    """A small tmpfs mounted at ``where`` (a full disk on demand), or a skip."""
    where.mkdir(exist_ok=True)
    options = f"size={size}" + (",ro" if readonly else "")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode}); "
                    "needs root with CAP_SYS_ADMIN")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def fill(directory: Path) -> None:
    """Fill the file system of ``directory`` to the last byte."""
    for name, chunk in (("filler", 4096), ("filler-tail", 1)):
        with contextlib.suppress(OSError), open(directory / name, "wb", buffering=0) as f:
            while True:
                f.write(b"\0" * chunk)


def no_temporary_files(directory: Path) -> bool:
    return not [n for n in os.listdir(directory) if n.startswith(".")]


# ---------------------------------------------------------------- devices are not replaced
def test_log_into_a_device_writes_through_and_keeps_the_device(tmp_path: Path) -> None:
    node = device(tmp_path / "n.asc", 1, 3)
    r = ucom("init", "--virtual", "armar3", "--log", str(node))
    assert r.exit_code == 0, r.stderr
    assert is_char_device(node)
    assert os.listdir(tmp_path) == ["n.asc"]


def test_a_full_device_is_a_write_error_and_stays_a_device(tmp_path: Path) -> None:
    full = device(tmp_path / "full", 1, 7)
    r = ucom("tree", "format", str(EYES), "-o", str(full))
    assert r.exit_code == 5, r.stderr
    assert r.stderr.strip() == f"ucom: cannot write: -o: {full}: No space left on device"
    assert is_char_device(full)
    assert os.listdir(tmp_path) == ["full"]


def test_a_fifo_is_written_through(tmp_path: Path) -> None:
    fifo = tmp_path / "tree.fifo"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()), daemon=True)
    reader.start()
    r = ucom("tree", "format", str(EYES), "-o", str(fifo))
    reader.join(timeout=30)
    assert r.exit_code == 0, r.stderr
    assert got and got[0].decode() == ucom("tree", "format", str(EYES)).stdout
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_a_block_device_or_directory_is_refused_before_anything_is_sent(
        tmp_path: Path) -> None:
    with pytest.raises(InputError, match="is a directory"):
        fileio.Output(tmp_path)
    if Path("/dev/loop0").exists() and stat.S_ISBLK(os.stat("/dev/loop0").st_mode):
        with pytest.raises(InputError, match="block device"):
            fileio.Output("/dev/loop0")
    (tmp_path / "d.asc").mkdir()
    r = ucom("init", "--virtual", "armar3", "--log", str(tmp_path / "d.asc"))
    assert r.exit_code == 3 and "is a directory" in r.stderr


# ---------------------------------------------------------------- links and modes
def test_a_link_stays_a_link_and_its_target_is_replaced(tmp_path: Path) -> None:
    real = tmp_path / "real.tree"
    real.write_text(EYES.read_text().replace("\n", "\n\n"))  # valid, not canonical
    link = tmp_path / "link.tree"
    link.symlink_to("real.tree")
    r = ucom("tree", "format", str(link), "-o", str(link))
    assert r.exit_code == 0, r.stderr
    assert link.is_symlink() and os.readlink(link) == "real.tree"
    assert real.read_text() == ucom("tree", "format", str(EYES)).stdout
    assert sorted(os.listdir(tmp_path)) == ["link.tree", "real.tree"]


def test_a_dangling_link_gets_its_target(tmp_path: Path) -> None:
    link = tmp_path / "out.asc"
    link.symlink_to("made.asc")
    assert ucom("init", "--virtual", "armar3", "--log", str(link)).exit_code == 0
    assert link.is_symlink() and (tmp_path / "made.asc").stat().st_size > 0


@pytest.mark.parametrize("writer", ["log", "tree", "dbc", "record"])
def test_every_writer_keeps_the_old_mode_and_gives_new_files_0644(
        tmp_path: Path, writer: str) -> None:
    pytest.importorskip("cantools") if writer == "dbc" else None

    def write(target: Path) -> Result:
        if writer == "log":
            return ucom("init", "--virtual", "armar3", "--log", str(target))
        if writer == "tree":
            return ucom("tree", "format", str(EYES), "-o", str(target))
        if writer == "dbc":
            return ucom("dbc", "-o", str(target), "--force")
        state = tmp_path / "state"
        if not state.exists():
            assert ucom("flash", str(IMAGE), "--virtual", "armar3", "--state",
                        str(state)).exit_code == 0
        return ucom("remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
                    "--for", "0.05", "--record", str(target))

    suffix = {"log": ".asc", "tree": ".tree", "dbc": ".dbc", "record": ".asc"}[writer]
    old_mask = os.umask(0o022)
    try:
        new = tmp_path / f"new{suffix}"
        r = write(new)
        assert r.exit_code == 0, r.stderr
        assert stat.S_IMODE(new.stat().st_mode) == 0o644
        kept = tmp_path / f"kept{suffix}"
        kept.write_text("old\n")
        kept.chmod(0o600)
        r = write(kept)
        assert r.exit_code == 0, r.stderr
        assert stat.S_IMODE(kept.stat().st_mode) == 0o600
        assert kept.read_text() != "old\n"
    finally:
        os.umask(old_mask)
    assert no_temporary_files(tmp_path)


def test_dash_is_standard_output_where_a_command_writes_one_file() -> None:
    r = ucom("tree", "format", str(EYES), "-o", "-")
    assert r.exit_code == 0, r.stderr
    assert r.stdout == ucom("tree", "format", str(EYES)).stdout
    assert not Path("-").exists()


# ---------------------------------------------------------------- full and read-only disks
def test_log_on_a_full_disk_keeps_the_old_file_and_exits_5(tmp_path: Path) -> None:
    with tmpfs(tmp_path / "disk") as disk:
        log = disk / "run.asc"
        log.write_text("the old log\n")
        fill(disk)
        r = ucom("init", "--virtual", "armar3", "--log", str(log))
        assert r.exit_code == 5, r.stderr
        assert "No space left on device" in r.stderr and "Traceback" not in r.stderr
        assert log.read_text() == "the old log\n"
        assert no_temporary_files(disk)


def test_a_read_only_directory_is_refused_before_anything_is_sent(tmp_path: Path) -> None:
    with tmpfs(tmp_path / "ro", readonly=True) as ro:
        for args in (["init", "--virtual", "armar3", "--log", str(ro / "x.asc")],
                     ["tree", "format", str(EYES), "-o", str(ro / "x.tree")]):
            r = ucom(*args)
            assert r.exit_code == 3, (args, r.stderr)
            assert "Read-only file system" in r.stderr and "nothing was written" in r.stderr


def test_params_dump_on_a_full_disk_writes_no_tree_and_keeps_the_old_ones(
        tmp_path: Path) -> None:
    state = tmp_path / "state"
    assert ucom("flash", str(IMAGE), "--virtual", "armar3", "--state",
                str(state)).exit_code == 0
    with tmpfs(tmp_path / "disk", "256k") as disk:
        out = disk / "tuned"
        out.mkdir()
        old = out / "head_right.tree"
        old.write_text("before\n")
        fill(disk)
        r = ucom("params", "dump", "armar3", "--virtual", "armar3", "--state", str(state),
                 "-o", f"{out}/", "--force")
        assert r.exit_code == 5, r.stderr
        assert "No space left on device" in r.stderr and "Traceback" not in r.stderr
        assert os.listdir(out) == ["head_right.tree"] and old.read_text() == "before\n"


def test_flash_state_on_a_full_disk_keeps_the_previous_flash_and_says_so(
        tmp_path: Path) -> None:
    with tmpfs(tmp_path / "disk", "2m") as disk:
        state = disk / "state"
        assert ucom("flash", str(IMAGE), "--virtual", "armar3", "--state",
                    str(state)).exit_code == 0
        before = {p.name: p.read_bytes() for p in state.iterdir()}
        fill(disk)
        r = ucom("flash", str(IMAGE), "--virtual", "armar3", "--state", str(state))
        assert r.exit_code == 5, r.stderr
        assert "state could not be saved" in r.stderr and "flash as it was" in r.stderr
        assert "bus error" not in r.stderr and "Traceback" not in r.stderr
        assert {p.name: p.read_bytes() for p in state.iterdir()} == before


def test_atomic_output_failing_at_the_rename_keeps_the_old_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "t.txt"
    target.write_text("before\n")

    def refuse(src: str, dst: str) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(WriteError, match="Input/output error"):
        fileio.write_text(target, "after\n")
    assert target.read_text() == "before\n" and os.listdir(tmp_path) == ["t.txt"]


def test_a_batch_is_all_or_none(tmp_path: Path) -> None:
    (tmp_path / "a").write_text("old a")
    with pytest.raises(RuntimeError), fileio.Batch() as batch:
        batch.write_text(tmp_path / "a", "new a")
        batch.write_text(tmp_path / "b", "new b")
        raise RuntimeError("the third one failed")
    assert sorted(os.listdir(tmp_path)) == ["a"] and (tmp_path / "a").read_text() == "old a"
    with fileio.Batch() as batch:
        batch.write_text(tmp_path / "a", "new a")
        batch.write_text(tmp_path / "b", "new b")
    assert (tmp_path / "a").read_text() == "new a" and (tmp_path / "b").read_text() == "new b"


# ---------------------------------------------------------------- standard output
def test_a_full_standard_output_is_one_line_and_exit_5() -> None:
    with open("/dev/full", "w") as full:
        r = run("init", "--virtual", "armar3", "--json", stdout=full.fileno())
    assert r.returncode == 5, r.stderr
    assert r.stderr.strip() == "ucom: cannot write: standard output: No space left on device"


def test_a_closed_pipe_ends_the_output_quietly_with_the_jobs_exit_code(
        tmp_path: Path) -> None:
    reader, writer = os.pipe()
    os.close(reader)  # nobody reads: the first write gets EPIPE, as under `| head -c0`
    try:
        r = run("flash", str(IMAGE), "--virtual", "armar3", "--state", str(tmp_path / "s"),
                stdout=writer)
    finally:
        os.close(writer)
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""
    again = run("check", "--virtual", "armar3", "--state", str(tmp_path / "s"), "--json")
    assert again.returncode == 0, again.stderr  # every board holds the verified program


# ---------------------------------------------------------------- inputs
@pytest.mark.parametrize("args", [["srec", "info"], ["tree", "check"], ["tree", "show"],
                                  ["init", "--virtual"]])
def test_a_directory_as_input_is_bad_input_not_usage(tmp_path: Path, args: list[str]) -> None:
    r = ucom(*args, str(tmp_path))
    assert r.exit_code == 3, r.stderr
    assert "is a directory" in r.stderr


@pytest.mark.parametrize(("what", "args", "limit"), [
    ("tree", ["tree", "check"], "4.0 MiB"),
    ("topology", ["init", "--virtual"], "4.0 MiB"),
    ("image", ["srec", "info"], None)])
def test_inputs_are_read_with_a_size_cap(tmp_path: Path, what: str, args: list[str],
                                         limit: str | None) -> None:
    big = tmp_path / f"big.{what}"
    big.write_text(IMAGE.read_text().splitlines()[0] + "\n" if what == "image"
                   else "# a comment\n")
    os.truncate(big, 200 * 1024 * 1024)  # 200 MB, sparse: costs no disk
    r = run(*args, str(big), timeout=30)
    assert r.returncode == 3, r.stderr
    assert "larger than" in r.stderr and "Traceback" not in r.stderr
    if limit:
        assert limit in r.stderr


def test_a_fifo_topology_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "robot.toml"
    os.mkfifo(fifo)
    r = ucom("init", "--virtual", str(fifo))
    assert r.exit_code == 3 and "is a FIFO, not a regular file" in r.stderr


# ---------------------------------------------------------------- numbers
def test_nan_in_a_topology_is_refused_naming_the_field(tmp_path: Path) -> None:
    topo = tmp_path / "t.toml"
    text = (ROOT / "tests" / "data" / "armar3_can0.toml").read_text()
    topo.write_text(text + "\n[timing]\nword_program_us = nan\n"
                    if "[timing]" not in text else text.replace("[timing]",
                                                                "[timing]\nword_program_us = nan"))
    r = ucom("init", "--virtual", str(topo))
    assert r.exit_code == 3, r.stderr
    assert "word_program_us" in r.stderr and "finite" in r.stderr


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_nan_and_inf_options_are_refused(value: str) -> None:
    r = ucom("decode", str(EYES), "--margin", value)
    assert r.exit_code == 2 and "not a finite number" in r.stderr


def test_a_topology_with_too_many_buses_is_refused(tmp_path: Path) -> None:
    topo = tmp_path / "many.toml"
    topo.write_text('name = "many"\n' + "".join(
        f'[[bus]]\nname = "CAN{i}"\n' for i in range(17)))
    r = ucom("fleet", "show", str(topo))
    assert r.exit_code == 3 and "at most 16 buses" in r.stderr


def test_remote_run_refuses_nan_durations_and_values(tmp_path: Path) -> None:
    r = ucom("remote", "run", "armar3", "--virtual", "armar3", "--for", "nan")
    assert r.exit_code == 2 and "'nan' is not a finite number" in r.stderr
    state = tmp_path / "state"
    assert ucom("flash", str(IMAGE), "--virtual", "armar3", "--state",
                str(state)).exit_code == 0
    r = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
             "--for", "0.05", "--set", "Right Eye Target=nan")
    assert r.exit_code == 3, r.stderr
    assert "Right Eye Target: nan is not a finite number" in r.stderr


def test_dbc_into_a_full_device_is_one_line_and_exit_5(tmp_path: Path) -> None:
    pytest.importorskip("cantools")
    full = device(tmp_path / "full.dbc", 1, 7)
    r = ucom("dbc", "-o", str(full), "--force")
    assert r.exit_code == 5, r.stderr
    assert r.stderr.strip() == f"ucom: cannot write: --output: {full}: No space left on device"
    assert is_char_device(full)
