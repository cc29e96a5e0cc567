"""Recording a run as MCAP (issue 36, part 1): ``remote run --record run.mcap`` over the
in-process ARMAR-III fleet, its consumers' process as it runs for real, read back with
the ``mcap`` package's reader (CRCs checked), a reader no one here wrote; ``decode`` and
``remote plot`` of the file, ``decode --to`` for CAN tools, ``--log FILE.mcap``, and
what is refused."""

from __future__ import annotations

import itertools
import json
import os
from collections import Counter, defaultdict
from collections.abc import Iterator
from decimal import Decimal
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from mcap.reader import make_reader

from ucom_tools.cli.main import cli

ROOT = Path(__file__).resolve().parent.parent
SENSOR = "Right Eye Joint Sensor"


def ucom(*args: str) -> Any:
    return CliRunner().invoke(cli, list(args))


def read(path: Path) -> dict[str, Any]:
    """Everything of an MCAP file as the mcap package reads it, CRCs checked."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        messages = [(schema, channel, message) for schema, channel, message
                    in reader.iter_messages(log_time_order=False)]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    by_topic: dict[str, list[Any]] = defaultdict(list)
    for schema, channel, message in messages:
        by_topic[channel.topic].append((schema, channel, message))
    return {"summary": summary, "topics": by_topic, "metadata": metadata}


@pytest.fixture(scope="module")
def state(tmp_path_factory: pytest.TempPathFactory) -> Path:
    s = tmp_path_factory.mktemp("mcap") / "state"
    r = ucom("flash", str(ROOT / "firmware_images/armar3.fl.S"), "--virtual", "armar3",
             "--state", str(s))
    assert r.exit_code == 0, r.stderr
    return s


@pytest.fixture(scope="module")
def run(state: Path) -> Iterator[tuple[Path, dict[str, Any], dict[str, Any]]]:
    """One second of ARMAR-III with the right eye sent to 200, recorded as MCAP and, by
    --log, as BLF (the same frames: both from the buses' dispatchers)."""
    out = state.parent
    r = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
             "--for", "1", "--set", "Right Eye Target=200", "--record",
             str(out / "run.mcap"), "--log", str(out / "run.blf"), "--json")
    assert r.exit_code == 0, r.stderr
    yield out / "run.mcap", json.loads(r.stdout), read(out / "run.mcap")


def test_frames_per_bus_agree_with_the_runs_own_counts(run) -> None:
    _, result, got = run
    counted = result["record"]["frames"]
    assert set(counted) == {"CAN0", "CAN1", "CAN2", "CAN3"}
    stats = got["summary"].statistics
    channels = got["summary"].channels
    per_topic = {channels[c].topic: n for c, n in stats.channel_message_counts.items()}
    for bus, n in counted.items():
        assert n > 5000  # a second of a 1 kHz exchange
        assert per_topic[f"/{bus}/frames"] == n == len(got["topics"][f"/{bus}/frames"])
    assert stats.message_count == sum(len(v) for v in got["topics"].values())
    schema, channel, message = got["topics"]["/CAN0/frames"][0]
    assert schema.name == "ucom.CanFrame" and schema.encoding == "jsonschema"
    assert json.loads(schema.data)["type"] == "object"
    assert channel.message_encoding == "json" and channel.metadata["bus"] == "CAN0"
    frame = json.loads(message.data)
    assert set(frame) == {"time", "id", "extended", "remote", "error", "direction", "dlc",
                          "data"}
    directions = Counter(json.loads(m.data)["direction"]
                         for _, _, m in got["topics"]["/CAN1/frames"])
    assert directions["rx"] > 0 and directions["tx"] > 0


def test_log_times_are_monotonic_per_channel_and_on_one_time_base(run) -> None:
    _, _, got = run
    for topic, items in got["topics"].items():
        times = [m.log_time for _, _, m in items]
        assert times == sorted(times), topic
        assert all(m.publish_time == m.log_time for _, _, m in items)
    offset = float(got["metadata"]["ucom.robot"]["clock_offset_s"])
    for topic in ("/CAN0/frames", "/Eyes/values"):  # log time = bus time + one offset
        for _, _, m in got["topics"][topic][::97]:
            bus_time = json.loads(m.data)["time"]
            assert abs(m.log_time - (bus_time + offset) * 1e9) < 2e3, topic
    frames = [json.loads(m.data)["time"] for _, _, m in got["topics"]["/CAN0/frames"]]
    values = [json.loads(m.data)["time"] for _, _, m in got["topics"]["/Eyes/values"]]
    assert frames[0] <= values[0] and values[-1] - frames[-1] < 0.01  # the same clock


def test_values_agree_with_the_runs_last_values(run) -> None:
    _, result, got = run
    boards = result["boards"]
    assert len(boards) == 11
    for board in boards:
        topic = f"/{board['prefix']}/values"
        items = got["topics"][topic]
        assert len(items) > 900, topic  # at the loop's rate, a second
        schema, channel, last = items[-1]
        assert schema.name == f"ucom.Values.{board['prefix']}"
        keys = {name: key for key, name, *_ in json.loads(channel.metadata["edges"])}
        body = json.loads(last.data, parse_float=Decimal)
        assert body["valid"] is True
        for edge in board["edges"]:
            if edge["text"] is None:  # not exchanged (an unused motor's sensor)
                assert keys[edge["name"]] not in body
                continue
            got_value = body[keys[edge["name"]]]
            assert Decimal(str(got_value)) == Decimal(edge["text"]), edge["name"]
    eyes = [json.loads(m.data)["Right_Eye_Joint_Sensor"]
            for _, _, m in got["topics"]["/Eyes/values"]]
    assert eyes[0] < 50 and eyes[-1] > 150  # the eye moved towards its target


def test_a_value_never_changed_is_in_every_message_from_the_start(run) -> None:
    """The left eye's target was never written (the right one's was, by --set): its
    value is in every message from the run's first snapshot on (a tenth of a second),
    as the boards were configured, so that a plot of it is drawn (Lichtblick showed
    nothing where a target was never set)."""
    _, result, got = run
    final = {e["name"]: e["text"] for b in result["boards"] for e in b["edges"]}
    messages = [json.loads(m.data) for _, _, m in got["topics"]["/Eyes/values"]]
    for key, name in (("Left_Eye_Target", "Left Eye Target"),
                      ("Left_Eye_Target_Vel", "Left Eye Target Vel")):
        having = [m for m in messages if key in m]
        assert len(having) > 0.85 * len(messages), key
        assert having[-1] is messages[-1] and \
            {str(m[key]) for m in having} == {final[name]}, key
    assert messages[-1]["Right_Eye_Target"] == 200


def test_joints_are_foxglove_joint_states(run) -> None:
    _, result, got = run
    items = got["topics"]["/joints"]
    assert items and items[0][0].name == "foxglove.JointStates"
    last = json.loads(items[-1][2].data)
    names = [j["name"] for j in last["joints"]]
    assert len(names) == 27 and "Right Eye" in names and "Torso Yaw" in names
    eye = next(j for j in last["joints"] if j["name"] == "Right Eye")
    edges = {e["name"]: e["value"] for b in result["boards"] for e in b["edges"]}
    assert eye["position"] == edges[SENSOR] and eye["velocity"] == edges["Right Eye Velocity"]
    assert last["timestamp"]["sec"] * 10**9 + last["timestamp"]["nsec"] == items[-1][2].log_time


def test_the_robots_structure_is_a_metadata_record(run) -> None:
    _, _, got = run
    meta = got["metadata"]["ucom.robot"]
    assert meta["robot"] == "ARMAR-III" and float(meta["loop_hz"]) == 1000.0
    assert set(json.loads(meta["buses"])) == {"CAN0", "CAN1", "CAN2", "CAN3"}
    boards = json.loads(meta["boards"])
    eyes = next(b for b in boards if b["prefix"] == "Eyes")
    assert (eyes["bus"], eyes["board"], eyes["topic"]) == ("CAN0", 3, "/Eyes/values")
    assert any(e["name"] == SENSOR and e["kind"] == "SO" and e["unit"] == "counts"
               for e in eyes["edges"])


def test_decode_reads_it_as_the_blf_of_the_same_frames(run) -> None:
    path, _, _ = run
    blf = path.with_suffix(".blf")
    a, b = ucom("decode", str(path)), ucom("decode", str(blf))
    assert a.exit_code == b.exit_code == 0, (a.stderr, b.stderr)
    assert a.stdout == b.stdout and "Init Request" in a.stdout
    ja, jb = (json.loads(ucom("decode", "--json", str(p)).stdout) for p in (path, blf))
    strip = lambda d: [[(m["t"], m["dir"], m["text"]) for x in bus["boards"]  # noqa: E731
                        for m in x["messages"]] for bus in d["buses"]]
    assert ja["frames"] == jb["frames"] and strip(ja) == strip(jb)


def test_decode_to_converts_for_can_tools_and_back(run, tmp_path: Path) -> None:
    path, _, _ = run
    out = tmp_path / "conv.blf"
    r = ucom("decode", str(path), "--to", str(out))
    assert r.exit_code == 0, r.stderr
    assert "frames of CAN0, CAN1, CAN2, CAN3" in r.stderr
    back = tmp_path / "back.mcap"
    assert ucom("decode", str(out), "--to", str(back)).exit_code == 0
    assert ucom("decode", str(back)).stdout == ucom("decode", str(path)).stdout
    r = ucom("decode", str(path), "--to", str(tmp_path / "one.csv"))
    assert r.exit_code == 3 and "could not be told apart" in r.stderr
    assert sorted(os.listdir(tmp_path)) == ["back.mcap", "conv.blf"]


def test_remote_plot_reads_the_values(run) -> None:
    path, result, _ = run
    r = ucom("remote", "plot", str(path), SENSOR, "Eyes/Right Eye Target", "--json")
    assert r.exit_code == 0, r.stderr
    series = json.loads(r.stdout)
    sensor = series[f"Eyes/{SENSOR}"]
    assert [p[1] for p in series["Eyes/Right Eye Target"]] == [200]
    ys = [y for _, y in sensor]
    assert all(a != b for a, b in itertools.pairwise(ys))  # changes only
    edges = {e["name"]: e["value"] for b in result["boards"] for e in b["edges"]}
    assert ys[-1] == edges[SENSOR]


def test_an_injected_fault_is_in_the_events_and_the_values(state: Path,
                                                           tmp_path: Path) -> None:
    scenario = tmp_path / "s.toml"
    scenario.write_text('[[fault]]\nat = 0.3\nbus = "CAN0"\nboard = 3\nkind = "power-off"\n'
                        'for = 0.3\n')
    path = tmp_path / "fault.mcap"
    r = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
             "--scenario", str(scenario), "--for", "1.5", "--on-fault", "hold", "--rejoin",
             "--record", str(path), "--record-rate", "100", "--json")
    assert r.exit_code == 0, r.stderr
    faults = json.loads(r.stdout)["faults"]
    assert [f["event"] for f in faults] == ["lost", "rejoined"]
    got = read(path)
    events = got["topics"]["/events"]
    assert events[0][0].name == "foxglove.Log"
    logs = [json.loads(m.data) for _, _, m in events]
    lost = next(x for x in logs if " lost at " in x["message"])
    back = next(x for x in logs if " rejoined at " in x["message"])
    assert lost["level"] == 3 and back["level"] == 2
    assert lost["name"] == "CAN0 board 3 (head right)"
    samples = [json.loads(m.data) for _, _, m in got["topics"]["/Eyes/values"]]
    assert 130 <= len(samples) <= 170  # --record-rate 100 for 1.5 s
    stale = [s["time"] for s in samples if not s["valid"]]
    t_lost = lost["timestamp"]["sec"] + lost["timestamp"]["nsec"] / 1e9
    offset = float(got["metadata"]["ucom.robot"]["clock_offset_s"])
    assert stale and abs(stale[0] - (t_lost - offset)) < 0.02
    assert samples[-1]["valid"]  # back after its rejoin
    neck = [json.loads(m.data)["valid"] for _, _, m in got["topics"]["/Neck/values"]]
    assert all(neck)


def test_log_mcap_on_a_bus_command(state: Path, tmp_path: Path) -> None:
    path = tmp_path / "check.mcap"
    r = ucom("remote", "check", "armar3", "--virtual", "armar3", "--state", str(state),
             "--log", str(path))
    assert r.exit_code == 0, r.stderr
    got = read(path)
    assert {t for t in got["topics"]} == {"/CAN0/frames", "/CAN1/frames", "/CAN2/frames",
                                          "/CAN3/frames"}
    d = ucom("decode", str(path))
    assert d.exit_code == 0 and "MCA DumpIO Descr" in d.stdout


def test_bad_input_writes_nothing(state: Path, tmp_path: Path) -> None:
    base = ["remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
            "--for", "0.1"]
    r = ucom(*base, "--record", str(tmp_path / "no" / "run.mcap"))
    assert r.exit_code == 3 and "does not exist" in r.stderr
    r = ucom(*base, "--record", str(tmp_path / "run.mcap"), "--record-rate", "5000")
    assert r.exit_code == 3 and "--record-rate" in r.stderr and "1000 Hz" in r.stderr
    r = ucom(*base, "--record", str(tmp_path / "run.blf"), "--record-rate", "10")
    assert r.exit_code == 3 and "MCAP recording only" in r.stderr
    r = ucom(*base, "--record", str(tmp_path / "run.mcap"), "--record-rate", "0")
    assert r.exit_code == 2
    assert os.listdir(tmp_path) == []


def test_a_write_failure_keeps_nothing(state: Path, tmp_path: Path) -> None:
    """The recording goes to a device that is always full (/dev/full, through a link
    named .mcap): the run ends as a failed write (exit 5), nothing kept."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    link = tmp_path / "full.mcap"
    link.symlink_to("/dev/full")
    r = ucom("remote", "run", "armar3", "--virtual", "armar3", "--state", str(state),
             "--for", "0.5", "--record", str(link))
    assert r.exit_code == 5, r.stderr
    assert "No space left on device" in r.stderr and "nothing was kept" in r.stderr


def test_a_damaged_file_is_bad_input(run, tmp_path: Path) -> None:
    path, _, _ = run
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    r = ucom("decode", str(cut))
    assert r.exit_code == 3 and "cut.mcap" in r.stderr
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data[:100] + bytes([data[100] ^ 0xFF]) + data[101:])
    r = ucom("remote", "plot", str(bad), SENSOR, "--json")
    assert r.exit_code == 3, r.stderr


def _panels(node: Any) -> Iterator[dict[str, Any]]:
    """Every panel of a layout in foxglove-sdk's form."""
    if node["type"] == "panel":
        yield node
    for child in node.get("tabs", []) + node.get("items", []):
        yield from _panels(child["content"])


def test_the_layout_plots_what_a_recording_holds(run, tmp_path: Path) -> None:
    """``remote layout``: every plotted path names a field of a topic the recording has
    (its schema lists it, its messages carry numbers there), the Log panel the events'
    topic and each raw-messages panel a bus's frames; the right eye's sensor is plotted
    against its target."""
    _, _, got = run
    out = tmp_path / "armar3.json"
    r = ucom("remote", "layout", "armar3", "-o", str(out))
    assert r.exit_code == 0, r.stderr
    panels = list(_panels(json.loads(out.read_text())["content"]))
    schemas = {topic: json.loads(msgs[0][0].data) for topic, msgs in got["topics"].items()}
    plotted = []
    for p in panels:
        if p["panelType"] == "Plot":
            for series in p["config"]["paths"]:
                topic, _, field = series["value"].partition(".")
                assert field in schemas[topic]["properties"], series["value"]
                values = [json.loads(m[2].data).get(field) for m in got["topics"][topic]]
                assert any(isinstance(v, int | float) for v in values), series["value"]
                plotted.append(series["value"])
        elif p["panelType"] == "Log":
            # the events' topic (written once a run has events, see the injected fault's
            # test above)
            assert p["config"]["topicToRender"] == "/events"
        else:
            assert p["panelType"] == "RawMessages", p["panelType"]
            assert p["config"]["topicPath"] in got["topics"]
    assert "/Eyes/values.Right_Eye_Joint_Sensor" in plotted
    assert "/Eyes/values.Right_Eye_Target" in plotted
    # the events and one bus's frames in tabs of their own: a client subscribes to what
    # the open tab shows, and every frame of four buses overwhelmed a browser
    tabs = {t["title"]: list(_panels(t["content"]))
            for t in json.loads(out.read_text())["content"]["tabs"]}
    assert [p["panelType"] for p in tabs["events"]] == ["Log"]
    assert [p["config"]["topicPath"] for p in tabs["frames"]] == ["/CAN0/frames"]
    assert sum(p["panelType"] == "RawMessages" for p in panels) == 1


def test_the_lichtblick_layout_holds_every_panel_once(tmp_path: Path) -> None:
    """``--for lichtblick``: Studio 1.x's form: every panel of the SDK's layout under an id
    in configById, each reached once from the layout's tree (tabs and binary splits),
    split shares between 0 and 100 %."""
    sdk, studio = tmp_path / "sdk.json", tmp_path / "studio.json"
    assert ucom("remote", "layout", "lauron4", "-o", str(sdk)).exit_code == 0
    r = ucom("remote", "layout", "lauron4", "-o", str(studio), "--for", "lichtblick")
    assert r.exit_code == 0, r.stderr
    doc = json.loads(studio.read_text())
    config = doc["configById"]
    reached: list[str] = []

    def walk(node: Any) -> None:
        if isinstance(node, str):
            reached.append(node)
            for tab in config[node].get("tabs", []) if node.startswith("Tab!") else []:
                walk(tab["layout"])
            return
        assert 0 < node["splitPercentage"] < 100 and node["direction"] in ("row", "column")
        walk(node["first"])
        walk(node["second"])

    walk(doc["layout"])
    assert sorted(reached) == sorted(config)
    sdk_panels = list(_panels(json.loads(sdk.read_text())["content"]))
    assert len(config) == len(sdk_panels) + 1  # and the Tab panel
    for key in ("lichtblickPanelTitle", "foxglovePanelTitle"):  # Lichtblick's, Studio's
        assert {p.get("title") for p in sdk_panels} <= {c.get(key) for c in config.values()}
    plots = [c for name, c in config.items() if name.startswith("Plot!")]
    assert plots
    for c in plots:  # what Lichtblick reads (a following view width empties a recording's)
        assert "followingViewWidth" not in c and "timeWindowMode" not in c
        for series in c["paths"]:
            assert "lineStyle" not in series and series["timestampMethod"] == "receiveTime"
            assert series["lineSize"] > 0 and series["color"].startswith("#")
        if len(c["paths"]) == 2:  # the value against its target: the target wider
            assert c["paths"][1]["lineSize"] > c["paths"][0]["lineSize"]


def test_the_layout_replaces_no_file_and_names_a_wrong_robot(tmp_path: Path) -> None:
    mine = tmp_path / "mine.json"
    mine.write_text("my layout")
    r = ucom("remote", "layout", "armar3", "-o", str(mine))
    assert r.exit_code == 3 and "exists; --force replaces it" in r.stderr
    assert mine.read_text() == "my layout"
    r = ucom("remote", "layout", "armar33", "-o", str(tmp_path / "x.json"))
    assert r.exit_code == 3 and "armar33" in r.stderr and not (tmp_path / "x.json").exists()
    assert ucom("remote", "layout", "armar3", "-o", str(mine), "--force").exit_code == 0
    assert json.loads(mine.read_text())["content"]["type"] == "tabs"


@pytest.mark.parametrize("flags", range(16))
def test_a_handed_over_frame_is_written_as_the_schema_says(flags: int) -> None:
    """The recorder's and the Foxglove feed's encoder (a table of the flags' fields)
    against json.dumps of what the schema names, for every combination of flags."""
    import base64

    from ucom_tools.protocol.traffic import ERROR, EXTENDED, REMOTE, SENT
    from ucom_tools.trace.mcapfile import FRAME_SCHEMA, entry_json, frame_json

    for ident, data in ((0x1ABCDEF, bytes(range(8))), (0x7FF, b""), (0x123, b"\xff")):
        entry = (ident, data, 1765161234.123457, flags)
        got = entry_json(entry)
        expected = {"time": 1765161234.123457, "id": ident,
                    "extended": bool(flags & EXTENDED), "remote": bool(flags & REMOTE),
                    "error": bool(flags & ERROR),
                    "direction": "tx" if flags & SENT else "rx", "dlc": len(data),
                    "data": base64.b64encode(data).decode()}
        assert json.loads(got) == expected and list(json.loads(got)) == list(expected)
        assert set(expected) == set(FRAME_SCHEMA["properties"])
        assert got == frame_json(1765161234.123457, ident, data,
                                 extended=bool(flags & EXTENDED),
                                 remote=bool(flags & REMOTE), error=bool(flags & ERROR),
                                 rx=not flags & SENT)
