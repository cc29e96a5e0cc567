"""The front door (issue 37, section 4): what a new user sees first, on the bundled
virtual fleet at 80 columns.  Tables fit without cutting a word, a serial or a ProgID in
two; the messages of the first tries say what is wrong and what to do.  (Every command's
help and its place in ucom(1)'s synopsis: tests/test_docs.py.)"""

from __future__ import annotations

import json
import os
import re
import selectors
import signal
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli
from ucom_tools.cli.tables import FitTable
from ucom_tools.image.formats import load_image

ROOT = Path(__file__).resolve().parent.parent
IMAGE = str(ROOT / "firmware_images/armar3.fl.S")
PROGID = f"0x{load_image(IMAGE).progid:08X}"
WIDTH = 80
NARROW = {"COLUMNS": str(WIDTH)}
DEADLINE_S = 60.0


def ucom(*args: str, env: dict[str, str] | None = None) -> Result:
    return CliRunner().invoke(cli, list(args), env=NARROW if env is None else env)


def js(r: Result) -> dict:
    assert r.stdout, r.stderr
    return json.loads(r.stdout)


def assert_fits(text: str, whole: Iterable[str]) -> None:
    """Every line within 80 columns and each of ``whole`` on one line, uncut."""
    too_wide = [line for line in text.splitlines() if len(line) > WIDTH]
    assert not too_wide, "\n".join(too_wide)
    cut = [w for w in whole if w not in text]
    assert not cut, (cut, text)


@pytest.fixture(scope="module")
def flashed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Result]:
    """ARMAR-III with armar3.fl.S in every board's flash: the state and the flash's
    output at 80 columns."""
    state = tmp_path_factory.mktemp("armar3")
    r = ucom("flash", IMAGE, "--virtual", "armar3", "--state", str(state))
    assert r.exit_code == 0, r.stderr
    return state, r


@pytest.fixture(scope="module")
def serials() -> list[str]:
    r = ucom("init", "--virtual", "armar3", "--json", "--no-info")
    return [b["serial"] for bus in js(r)["buses"] for b in bus["boards"]]


# ---------------------------------------------------------------------- tables
def test_flash_table_keeps_serials_progids_and_words_whole(flashed, serials) -> None:
    _, r = flashed
    assert_fits(r.stdout, [*serials, PROGID, "verified", "placement", "shoulder"])
    assert "11 of 11 board(s) verified" in r.stdout
    # resent, AutoStart and started are empty in a plain flash: left out
    assert "resent" not in r.stdout and "AutoSt" not in r.stdout and "started" not in r.stdout


def test_list_and_info_leave_out_secondary_columns_and_say_which(flashed, serials) -> None:
    state, _ = flashed
    for command in ("list", "info"):
        args = [command] + (["all"] if command == "info" else [])
        r = ucom(*args, "--virtual", "armar3", "--state", str(state), "--init")
        assert r.exit_code == 0, r.stderr
        assert_fits(r.stdout, [*serials, PROGID, "bootloader", "armar3.fl.S"])
        assert "left out at 80 columns: size, programmed, plug-on" in r.stdout
        assert "flags" not in r.stdout  # no board has a flag set: an empty column
    wide = ucom("list", "--virtual", "armar3", "--state", str(state), "--init",
                env={"COLUMNS": "200"})
    assert "programmed" in wide.stdout and "left out" not in wide.stdout


def test_info_of_one_board_speaks_words_and_json_keeps_its_keys(flashed) -> None:
    state, _ = flashed
    args = ("info", "2", "--bus", "CAN1", "--virtual", "armar3", "--state", str(state),
            "--init")
    r = ucom(*args)
    assert r.exit_code == 0, r.stderr
    rows = {line.strip("│ ").split("│")[0].strip(): line.split("│")[2].strip()
            for line in r.stdout.splitlines() if line.count("│") == 3}
    assert rows["seq ID"] == "2" and rows["ProgID"] == PROGID
    assert rows["flash valid"] == "yes" and rows["AutoStart"] == "no"
    for field_name in ("seq_id", "flash_valid", "prog_enable", "False", "True"):
        assert field_name not in r.stdout
    (board,) = js(ucom(*args, "--json"))["boards"]
    assert board["flash_valid"] is True and board["autostart"] is False
    assert board["seq_id"] == 2 and board["progid"] == PROGID


def test_fleet_show_fits_and_drops_the_empty_columns() -> None:
    r = ucom("fleet", "show", "armar3")
    assert r.exit_code == 0, r.stderr
    assert_fits(r.stdout, ["placement", "bootloader", "shoulder", "platform"])
    # at power-on no board has a seq ID or an exchange yet: those columns are left out
    assert "exchange" not in r.stdout and "seq ID" not in r.stdout


def test_remote_check_shows_bundled_trees_by_their_short_name(flashed) -> None:
    state, _ = flashed
    r = ucom("remote", "check", "--virtual", "armar3", "--state", str(state))
    assert r.exit_code == 0, r.stderr
    assert_fits(r.stdout, ["armar3/neck.tree", "armar3/right_shoulder_front.tree",
                           "RightShoulder", "matches"])
    assert str(ROOT) not in r.stdout


def test_remote_runs_start_table_fits(flashed, tmp_path) -> None:
    """A board whose tree is another robot's: the table of the start names each tree
    short, fits 80 columns, and nothing starts."""
    state, _ = flashed
    text = (ROOT / "ucom_tools/config/topologies/armar3.toml").read_text()
    text = text.replace('tree = "attribute_trees/armar3/head_right.tree"',
                        f'tree = "{ROOT}/attribute_trees/lauron4/front_left_leg.tree"')
    text = text.replace('tree = "attribute_trees/', f'tree = "{ROOT}/attribute_trees/')
    topology = tmp_path / "armar3_wrong.toml"
    topology.write_text(text)
    r = ucom("remote", "run", "--virtual", str(topology), "--state", str(state), "--for",
             "0.1")
    assert r.exit_code == 1
    table = r.stdout[:r.stdout.index("└")]
    assert_fits(table, ["lauron4/front_left_leg.tree", "armar3/neck.tree", "matches",
                        "differences"])
    assert str(ROOT) not in table
    assert "do not match their trees" in r.stderr


def test_conformance_list_wraps_its_sentences_within_80_columns() -> None:
    r = ucom("conformance", "--list")
    assert r.exit_code == 0, r.stderr
    cases = js(ucom("conformance", "--list", "--json"))["cases"]
    flowed = " ".join(r.stdout.split())
    assert_fits(r.stdout, [c["id"] for c in cases])
    for c in cases:
        assert " ".join(c["title"].split()) in flowed
        assert " ".join(c["section"].split()) in flowed
    # also piped (no width): no sentence runs on past 80 columns
    piped = ucom("conformance", "--list", env={})
    assert max(map(len, piped.stdout.splitlines())) <= WIDTH


def test_fit_table_breaks_no_word_where_the_words_fit() -> None:
    from rich.console import Console

    t = FitTable("t")
    for header, drop in (("name", 0), ("serial", 0), ("note", 1), ("empty", 0)):
        t.add_column(header, drop=drop)
    t.add_row("right shoulder front", "0xD92172BB", "a long remark of many words", "")
    t.add_row("neck", "0xAE26422D", "-", "-")
    console = Console(width=30, record=True, file=open(os.devnull, "w"))  # noqa: SIM115
    console.print(t)
    text = console.export_text()
    assert_fits(text, ["0xD92172BB", "0xAE26422D", "shoulder"])
    assert "empty" not in text and "left out at 30 columns: note" in text


# ---------------------------------------------------------------------- messages
def test_remote_run_on_empty_boards_says_so_in_one_short_line() -> None:
    for command in ("run", "check"):
        r = ucom("remote", command, "armar3", "--virtual", "armar3",
                 *(["--for", "1"] if command == "run" else []))
        assert r.exit_code == 1
        errors = [line for line in r.stderr.splitlines() if line.startswith("ucom:")]
        assert len(errors) == 1 and len(errors[0]) < 400, errors
        assert "11 board(s) hold no program to start" in errors[0]
        assert "flash first" in errors[0] and "--state DIR" in errors[0]
        assert "do not match" not in r.stderr and "boards against" not in r.stdout


def test_a_run_that_moved_nothing_says_it_once(flashed) -> None:
    state, _ = flashed
    r = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
             "--for", "0.5")
    assert r.exit_code == 0, r.stderr
    (said,) = [line for line in r.stdout.splitlines() if "moved" in line]
    assert re.fullmatch(r"no sensor value moved by more than one count: \d+ changed by one "
                        r"count or a flag only \(--json lists every value\)", said), said
    assert "more changed" not in r.stdout


def test_params_dump_says_what_its_counts_mean(flashed, tmp_path) -> None:
    state, _ = flashed
    r = ucom("params", "dump", "armar3", "--virtual", "armar3", "--state", str(state), "-o",
             str(tmp_path / "dump"))
    assert r.exit_code == 0, r.stderr
    assert "changed" not in r.stdout
    flowed = " ".join(r.stdout.split())
    assert "differ from tree: live values other than the default their tree gives" in flowed
    assert "power-on values" in flowed
    assert_fits(r.stdout[:r.stdout.index("└")], ["Neck", "RightShoulder"])


@pytest.mark.parametrize("args", [
    ("fleet", "show", "armr3"), ("init", "--virtual", "ARMAR3"),
    ("remote", "check", "armar", "--virtual", "armar3"), ("tree", "check", "--topology",
                                                         "armar3.toml")])
def test_a_misspelt_robot_gets_did_you_mean(args: tuple[str, ...]) -> None:
    r = ucom(*args)
    assert r.exit_code == 3, r.output
    assert "no such topology file; did you mean armar3?" in r.stderr


def test_a_name_like_no_robot_gets_the_list_only() -> None:
    r = ucom("fleet", "show", "xyz")
    assert r.exit_code == 3
    assert "did you mean" not in r.stderr and "bundled ones: armar3" in r.stderr


@pytest.mark.parametrize(("sig", "code", "said"), [(signal.SIGINT, 130, "interrupted"),
                                                   (signal.SIGTERM, 143, "terminated")])
def test_fleet_serve_exits_as_ucom_1_says_when_stopped(sig: int, code: int, said: str,
                                                      ) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "ucom_tools", "fleet", "serve", "armar3", "--port", "0",
         "--processes", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"), cwd=ROOT)
    try:
        assert proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            assert sel.select(timeout=DEADLINE_S), "the server did not start"
        assert proc.stdout.readline().startswith("listening on 127.0.0.1:")
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=DEADLINE_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == code, err
    assert said in err and "Traceback" not in err
