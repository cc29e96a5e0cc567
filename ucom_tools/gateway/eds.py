"""The files ``ucom gateway eds`` writes: an EDS per joint (CiA 306), the ``bus.yml`` that
Lely's ``dcfgen`` and ros2_canopen take, and the node table (``man/ucom-gateway.7``).

EDS: [FileInfo], [DeviceInfo] (SimpleBootUpSlave=1, NrOfRXPDO/NrOfTXPDO, Granularity=8),
[DummyUsage], the [MandatoryObjects]/[OptionalObjects]/[ManufacturerObjects] lists, then
one section per object and sub-index in index order, each with ParameterName,
ObjectType, DataType, AccessType, DefaultValue, PDOMapping and, where the value has
them, LowLimit and HighLimit.  Values are written so that both Lely (``dcfchk``,
``dcfgen``) and canopen (``import_od``) read them: signed numbers in decimal (``-1000``,
never canopen's own ``0x-3E8``), unsigned ones in hex (``0x6040``), COB-IDs with
the joint's node ID in (``0x187``, not ``$NODEID+0x180``: the EDS is its node's, and
``dcfchk`` reads it without ``-n``), the device name as its text; no REAL32.  No dates:
the same robot gives the same bytes.

bus.yml: ``options: dcf_path`` (where the master finds the ``.bin`` files dcfgen writes),
``master:`` (node ID :data:`MASTER_NODE` unless told otherwise, ros2_canopen's master
driver, SYNC every :data:`SYNC_PERIOD_US`, its heartbeat every :data:`MASTER_HEARTBEAT_MS`)
and one top-level key per joint, its lower snake case name, with ``node_id``, ``dcf``
(its EDS, relative: run dcfgen in the directory), ros2_canopen's CiA 402 driver,
``heartbeat_consumer: true`` (the node watches the master's heartbeat: dcfgen fills in
0x1016) and its PDOs as the EDS maps them (the master sets them at every boot).  Nodes
are listed in node ID order.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ucom_tools import __version__, fileio
from ucom_tools.errors import InputError, OutputExists
from ucom_tools.gateway import dictionary as od
from ucom_tools.gateway.dictionary import DataType, Dictionary, Entry, ObjectType
from ucom_tools.gateway.joints import Joint, RobotJoints, Role

MASTER_NODE = 1
"""The master's node ID in bus.yml (``--master-node``)."""
SYNC_PERIOD_US = 10_000
"""bus.yml ``sync_period``: 100 Hz, as ros2_canopen's examples."""
MASTER_HEARTBEAT_MS = 100
"""bus.yml master ``heartbeat_producer``: the nodes consume it (times dcfgen's
heartbeat multiplier, 3: a master silent for 300 ms is gone)."""
DRIVER_PERIOD_MS = 10
"""bus.yml ``period`` of ros2_canopen's CiA 402 driver."""
BUS_FILE = "bus.yml"


# ------------------------------------------------------------------------------ EDS
def _number(data_type: DataType, value: int) -> str:
    return str(value) if data_type.signed else f"0x{value:X}"


def value_text(entry: Entry) -> str:
    """An entry's DefaultValue as the EDS writes it."""
    if isinstance(entry.default, str):
        return entry.default
    return _number(entry.data_type, entry.default)


def _entry_lines(e: Entry) -> list[str]:
    lines = [f"ParameterName={e.name}", f"ObjectType=0x{int(ObjectType.VAR):X}",
             f"DataType=0x{int(e.data_type):04X}", f"AccessType={e.access.value}",
             f"DefaultValue={value_text(e)}", f"PDOMapping={int(e.pdo_mappable)}"]
    if e.low is not None:
        lines.append(f"LowLimit={_number(e.data_type, e.low)}")
    if e.high is not None:
        lines.append(f"HighLimit={_number(e.data_type, e.high)}")
    return lines


def _section(name: str, lines: Sequence[str]) -> str:
    return "\n".join((f"[{name}]", *lines)) + "\n"


def _list(name: str, objects: Sequence[od.Object]) -> str:
    return _section(name, [f"SupportedObjects={len(objects)}",
                           *(f"{n}=0x{o.index:04X}" for n, o in enumerate(objects, 1))])


MANDATORY = (0x1000, 0x1001, 0x1018)
"""[MandatoryObjects] (CiA 301: device type, error register, identity)."""


def _free_text(text: str) -> str:
    """Free text for an EDS line: ASCII (others become ``?``), without ``;`` and ``#``,
    which start comments there."""
    text = text.encode("ascii", "replace").decode("ascii")
    return " ".join(text.replace(";", ",").replace("#", "No.").split())


def eds_text(d: Dictionary) -> str:
    """The EDS of a joint's dictionary."""
    dev = d.device
    parts = [
        _section("FileInfo", [
            f"FileName={d.key}.eds", "FileVersion=1", "FileRevision=0", "EDSVersion=4.0",
            f"Description={_free_text(d.description)}",
            f"CreatedBy=ucom-tools {__version__}"]),
        _section("DeviceInfo", [
            f"VendorName={dev.vendor_name}", f"VendorNumber=0x{dev.vendor_number:08X}",
            f"ProductName={dev.product_name}", f"ProductNumber=0x{dev.product_number:08X}",
            f"RevisionNumber=0x{dev.revision_number:08X}", "OrderCode=",
            *(f"BaudRate_{k}=1" for k in od.BAUD_RATES_KBIT),
            "SimpleBootUpMaster=0", f"SimpleBootUpSlave={int(dev.simple_boot_up_slave)}",
            f"Granularity={dev.granularity}", "DynamicChannelsSupported=0",
            "GroupMessaging=0", f"NrOfRXPDO={dev.nr_rxpdo}", f"NrOfTXPDO={dev.nr_txpdo}",
            "LSS_Supported=0"]),
        _section("DummyUsage", [f"Dummy{n:04X}={int(DataType(n) in dev.dummies)}"
                                for n in range(1, 8)]),
        _list("MandatoryObjects", [o for o in d.objects if o.index in MANDATORY]),
        _list("OptionalObjects", [o for o in d.objects if o.index not in MANDATORY
                                  and not 0x2000 <= o.index < 0x6000]),
        _list("ManufacturerObjects", [o for o in d.objects if 0x2000 <= o.index < 0x6000]),
    ]
    for o in d.objects:
        if o.object_type is ObjectType.VAR:
            parts.append(_section(f"{o.index:04X}", _entry_lines(o.entries[0])))
            continue
        parts.append(_section(f"{o.index:04X}", [
            f"ParameterName={o.name}", f"ObjectType=0x{int(o.object_type):X}",
            f"SubNumber=0x{len(o.entries):X}"]))
        parts += [_section(f"{o.index:04X}sub{e.subindex:X}", _entry_lines(e))
                  for e in o.entries]
    return "\n".join(parts)


# -------------------------------------------------------------------------- bus.yml
def _quoted(text: str) -> str:
    """A YAML double-quoted scalar (JSON's escapes are YAML's)."""
    return json.dumps(text, ensure_ascii=False)


def bus_yml(robot: RobotJoints, *, master_node: int = MASTER_NODE,
            dcf_path: str | None = None) -> str:
    """The bus.yml of ``robot``'s joints; InputError (key ``master_node``) when a joint
    has the master's node ID."""
    for j in robot.joints:
        if j.node_id == master_node:
            raise InputError(f"node {master_node} is {j.name}'s ({j.where}, axis "
                             f"{j.letter}); give the master another ID", key="master_node")
    lines = [f"# ros2_canopen bus configuration: the joints of {robot.topology.name} as "
             "CiA 402 drives,",
             f"# written by 'ucom gateway eds' (ucom-tools {__version__}); see "
             "ucom-gateway(7).",
             "# In this directory, 'dcfgen -r bus.yml' (Lely dcf-tools) writes master.dcf "
             "and a .bin per joint."]
    if dcf_path:
        lines += ["options:", f"  dcf_path: {_quoted(dcf_path)}"]
    lines += ["master:", f"  node_id: {master_node}",
              '  driver: "ros2_canopen::MasterDriver"', '  package: "canopen_master_driver"',
              f"  sync_period: {SYNC_PERIOD_US}", f"  heartbeat_producer: {MASTER_HEARTBEAT_MS}"]
    for j in sorted(robot.joints, key=lambda j: j.node_id):
        lines += [f"{j.key}:  # {_free_text(j.name)}: {_free_text(j.where)}, axis {j.letter}",
                  f"  node_id: {j.node_id}", f"  dcf: {_quoted(j.key + '.eds')}",
                  '  driver: "ros2_canopen::Cia402Driver"', '  package: "canopen_402_driver"',
                  f"  period: {DRIVER_PERIOD_MS}", "  heartbeat_consumer: true",
                  *_pdo_lines("tpdo", od.TPDO_MAPS, 1), *_pdo_lines("rpdo", od.RPDO_MAPS, 255)]
    return "\n".join(lines) + "\n"


def _pdo_lines(what: str, maps: Sequence[Sequence[int]], transmission: int) -> list[str]:
    """A joint's PDOs as its EDS maps them, so that the master sets them at every boot
    (dcfgen puts them in the joint's .bin; without any, it leaves the .bin out of
    master.dcf)."""
    lines = [f"  {what}:"]
    for n in range(od.PDOS):
        lines.append(f"    {n + 1}:")
        if n >= len(maps):
            lines.append("      enabled: false")
            continue
        lines += ["      enabled: true", '      cob_id: "auto"',
                  f"      transmission: 0x{transmission:02X}", "      mapping:"]
        lines += [f"        - {{index: 0x{index:04X}, sub_index: 0}}" for index in maps[n]]
    return lines


# ----------------------------------------------------------------------- node table
def node_row(j: Joint) -> dict[str, Any]:
    """One joint of the node table (its --json form)."""
    return {"node_id": j.node_id, "given": j.node_given, "name": j.name, "key": j.key,
            "bus": j.bus, "board": j.board.position + 1, "placement": j.board.placement,
            "axis": j.letter, "program": j.board.program.name, "eds": f"{j.key}.eds",
            "target": j.unique(Role.TARGET)}


# ---------------------------------------------------------------------------- files
@dataclass(frozen=True)
class OutputFile:
    """One file of the output directory and its content."""

    name: str
    data: bytes


def render(robot: RobotJoints, *, master_node: int = MASTER_NODE,
           dcf_path: str | None = None) -> tuple[OutputFile, ...]:
    """Every file for ``robot``: an EDS per joint (in topology order), then bus.yml."""
    files = [OutputFile(f"{j.key}.eds", eds_text(od.build(j)).encode("ascii"))
             for j in robot.joints]
    files.append(OutputFile(BUS_FILE, bus_yml(robot, master_node=master_node,
                                              dcf_path=dcf_path).encode()))
    return tuple(files)


@dataclass(frozen=True)
class Written:
    """What :func:`write` did."""

    written: tuple[Path, ...]
    unchanged: tuple[Path, ...]
    """Files that held these bytes already (not rewritten)."""


def write(files: Sequence[OutputFile], directory: Path, *, force: bool = False) -> Written:
    """Write ``files`` into ``directory`` (made if missing), all or none, each atomically.
    A file there with other content is refused (OutputExists, key ``directory``, nothing
    written) unless ``force``; one with the same content is left as it is."""
    if directory.exists() and not directory.is_dir():
        raise InputError(f"{directory}: is not a directory; nothing was written",
                         key="directory")
    changed: list[tuple[Path, bytes]] = []
    same: list[Path] = []
    differ: list[str] = []
    for f in files:
        path, data = directory / f.name, f.data
        old = _content(path)
        if old == data:
            same.append(path)
            continue
        if old is not None and not force:
            differ.append(str(path))
        changed.append((path, data))
    if differ:
        raise OutputExists(differ, key="directory", detail=" with other content")
    if changed:
        fileio.prepare_directory(directory, key="directory")
        with fileio.Batch(key="directory") as batch:
            for path, data in changed:
                batch.write_bytes(path, data)
    return Written(tuple(p for p, _ in changed), tuple(same))


def _content(path: Path) -> bytes | None:
    """The bytes of an existing file (None when there is none); InputError for something
    in its place that is not a regular file."""
    if not path.exists() and not path.is_symlink():
        return None
    if path.is_dir():
        raise InputError(f"{path}: is a directory; nothing was written", key="directory")
    try:
        return fileio.read_input(path, limit=fileio.TEXT_LIMIT, what="a file")
    except InputError:
        return b""  # a device, a FIFO, a huge file: something else, never ours
