"""The object dictionary of one joint's CANopen node (CiA 301, CiA 402), as pure data.

:func:`build` makes a :class:`Dictionary` from a :class:`~ucom_tools.gateway.joints.Joint`
and the encodings of its board's edges; :func:`to_canopen` gives canopen's
``ObjectDictionary`` of it (for ``LocalNode``); :mod:`ucom_tools.gateway.eds` writes it
as an EDS.  ``man/ucom-gateway.7`` lists every object.

- Communication (CiA 301): 0x1000 device type :data:`DEVICE_TYPE` (CiA 402, servo drive),
  0x1001 error register, 0x1003 error history (:data:`ERROR_HISTORY` entries), 0x1005
  COB-ID SYNC, 0x1006 cycle period, 0x1008 device name (the joint's name), 0x1014/0x1015
  EMCY, 0x1016 consumer heartbeat (:data:`HEARTBEAT_CONSUMERS` entries), 0x1017 producer
  heartbeat (:data:`HEARTBEAT_MS`), 0x1018 identity (vendor 0, product = CRC-32 of the
  program's name, revision = the ProgID of the board's image, serial = the board's
  serial where the topology gives it); four RPDOs and TPDOs (0x1400-0x1403,
  0x1600-0x1603, 0x1800-0x1803, 0x1A00-0x1A03) mapped as ros2_canopen's examples map a
  CiA 402 drive: TPDO1 = 0x6041 + 0x6061, TPDO2 = 0x6064 + 0x606C (transmission type 1,
  every SYNC), RPDO1 = 0x6040 + 0x6060, RPDO2 = 0x607A + 0x60FF (type 255: at once);
  PDO 3 and 4 disabled and empty.
- CiA 402 (the joint's axis): controlword, statusword, modes, position and velocity,
  with limits from the edges they stand for (0x607A: the Target's range, 0x60FF:
  TargetVel's, 0x607D: Min/Max Position's, 0x6081: Max Velocity's times the program's
  velocity scale); 0x6502 supported modes (:class:`Mode`).
- Manufacturer (every edge of the board): PAR edge i at 0x2000 + i, CI edge i at
  0x3000 + i, SO edge i at 0x4000 + i (i counted per kind, as MCA does), sub-index 0;
  ParameterName = the edge's unique name, the data type from its width and sign,
  LowLimit/HighLimit its raw range, default its tree's default (raw); SO read-only.

Every value is raw, as the edges carry it (positions in joint sensor counts).
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from enum import IntEnum, IntFlag, StrEnum

from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from ucom_tools.edgelists.model import EdgeKind, EdgeSpec
from ucom_tools.errors import InputError
from ucom_tools.gateway.cia402_objects import ObjectValues
from ucom_tools.gateway.joints import BoardEdge, Joint, Role

DEVICE_TYPE = 0x00020192
"""0x1000: CiA 402 (0x192), servo drive (type 0x02)."""
HEARTBEAT_MS = 100
"""0x1017 default: a heartbeat every 100 ms."""
ERROR_HISTORY = 8
"""Entries of 0x1003."""
HEARTBEAT_CONSUMERS = 4
"""Entries of 0x1016 (a master and a few others to watch)."""
PDOS = 4
"""RPDOs and TPDOs each (0x1400-0x1403 ...)."""
MAP_ENTRIES = 8
"""Entries of each PDO mapping record (64 bits of 8-bit objects)."""
POSITION_WINDOW = 5
"""0x6067 default [counts]: the armar3 program's Settled tolerance."""
POSITION_WINDOW_MS = 20
"""0x6068 default [ms]: how long the armar3 program's Settled waits."""
_DRIVE = ObjectValues()
"""The drive's own defaults of the objects a master may change (its windows)."""
HOMING_METHOD = -1
"""0x6098's default: the program's own homing (drive at Reset PWM to the end stop, then the
counter takes Reset Offset), a manufacturer-specific method; -3 and -4 do the same towards
the negative or positive end stop (:func:`~ucom_tools.gateway.cia402_modes.reset_pwm_for`)."""
MANUFACTURER_BASE = {EdgeKind.PAR: 0x2000, EdgeKind.CI: 0x3000, EdgeKind.SO: 0x4000}
"""Index of edge 0 of each kind; edge i is at base + i."""
MAX_EDGES = 0x1000
"""Edges of one kind that fit below the next base."""


class DataType(IntEnum):
    """CiA 301 data types the dictionaries use."""

    BOOLEAN = 0x01
    INTEGER8 = 0x02
    INTEGER16 = 0x03
    INTEGER32 = 0x04
    UNSIGNED8 = 0x05
    UNSIGNED16 = 0x06
    UNSIGNED32 = 0x07
    VISIBLE_STRING = 0x09

    @property
    def signed(self) -> bool:
        return self in (DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER32)

    @property
    def bits(self) -> int:
        return _BITS[self]


_BITS = {DataType.BOOLEAN: 1, DataType.INTEGER8: 8, DataType.INTEGER16: 16,
         DataType.INTEGER32: 32, DataType.UNSIGNED8: 8, DataType.UNSIGNED16: 16,
         DataType.UNSIGNED32: 32, DataType.VISIBLE_STRING: 0}


class Access(StrEnum):
    """CiA 306 AccessType."""

    RO = "ro"
    RW = "rw"
    CONST = "const"


class ObjectType(IntEnum):
    """CiA 306 ObjectType."""

    VAR = 0x7
    ARRAY = 0x8
    RECORD = 0x9


class Mode(IntEnum):
    """CiA 402 modes of operation (0x6060) the gateway drives."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6
    CYCLIC_SYNC_POSITION = 8


class SupportedModes(IntFlag):
    """0x6502 bits."""

    PP = 1 << 0
    PV = 1 << 2
    HM = 1 << 5
    CSP = 1 << 7


@dataclass(frozen=True)
class Entry:
    """One value of the dictionary: a VAR object, or one sub-index of an ARRAY/RECORD."""

    index: int
    subindex: int
    name: str
    data_type: DataType
    access: Access
    default: int | str
    low: int | None = None
    high: int | None = None
    pdo_mappable: bool = False


@dataclass(frozen=True)
class Object:
    """One index: a VAR (one entry, sub-index 0), an ARRAY or a RECORD."""

    index: int
    name: str
    object_type: ObjectType
    entries: tuple[Entry, ...]

    def entry(self, subindex: int) -> Entry:
        for e in self.entries:
            if e.subindex == subindex:
                return e
        raise KeyError((self.index, subindex))


@dataclass(frozen=True)
class DeviceInfo:
    """What the EDS's [DeviceInfo] says."""

    vendor_name: str
    vendor_number: int
    product_name: str
    product_number: int
    revision_number: int
    nr_rxpdo: int = PDOS
    nr_txpdo: int = PDOS
    granularity: int = 8
    simple_boot_up_slave: bool = True
    dummies: tuple[DataType, ...] = (DataType.INTEGER8, DataType.INTEGER16,
                                     DataType.INTEGER32, DataType.UNSIGNED8,
                                     DataType.UNSIGNED16, DataType.UNSIGNED32)
    """Data types a PDO may map as a dummy (a gap)."""


@dataclass(frozen=True)
class Dictionary:
    """The object dictionary of one joint's node."""

    name: str
    """The joint's name (0x1008)."""
    key: str
    """The joint's bus.yml key (the EDS file's base name)."""
    node_id: int
    description: str
    device: DeviceInfo
    objects: tuple[Object, ...]
    """In index order."""

    def object(self, index: int) -> Object:
        for o in self.objects:
            if o.index == index:
                return o
        raise KeyError(index)

    def entry(self, index: int, subindex: int = 0) -> Entry:
        return self.object(index).entry(subindex)

    @property
    def entries(self) -> tuple[Entry, ...]:
        return tuple(e for o in self.objects for e in o.entries)


# ------------------------------------------------------------------------- building
def _var(index: int, name: str, data_type: DataType, access: Access, default: int | str,
         *, low: int | None = None, high: int | None = None, pdo: bool = False) -> Object:
    return Object(index, name, ObjectType.VAR, (Entry(index, 0, name, data_type, access,
                                                      default, low, high, pdo),))


def _compound(index: int, name: str, object_type: ObjectType, access0: Access,
              subs: Iterable[tuple[int, str, DataType, Access, int]]) -> Object:
    """An ARRAY or RECORD: sub-index 0 holds the highest sub-index (UNSIGNED8)."""
    subs = list(subs)
    highest = max(s[0] for s in subs)
    first = Entry(index, 0, "Highest sub-index supported", DataType.UNSIGNED8, access0,
                  highest)
    return Object(index, name, object_type, (first, *(
        Entry(index, sub, n, dt, acc, default)
        for sub, n, dt, acc, default in subs)))


def _communication(joint: Joint) -> list[Object]:
    u8, u16, u32 = DataType.UNSIGNED8, DataType.UNSIGNED16, DataType.UNSIGNED32
    ro, rw = Access.RO, Access.RW
    board = joint.board
    errors = [(i, f"Standard error field {i}", u32, ro, 0) for i in range(1, ERROR_HISTORY + 1)]
    history = _compound(0x1003, "Pre-defined error field", ObjectType.ARRAY, rw, errors)
    history = Object(history.index, history.name, history.object_type, (
        Entry(0x1003, 0, "Number of errors", u8, rw, 0), *history.entries[1:]))
    consumers = [(i, f"Consumer heartbeat time {i}", u32, rw, 0)
                 for i in range(1, HEARTBEAT_CONSUMERS + 1)]
    return [
        _var(0x1000, "Device type", u32, ro, DEVICE_TYPE),
        _var(0x1001, "Error register", u8, ro, 0, pdo=True),
        history,
        _var(0x1005, "COB-ID SYNC", u32, rw, 0x80),
        _var(0x1006, "Communication cycle period", u32, rw, 0),
        _var(0x1008, "Manufacturer device name", DataType.VISIBLE_STRING, Access.CONST,
             joint.name),
        _var(0x1014, "COB-ID EMCY", u32, rw, 0x80 + joint.node_id),
        _var(0x1015, "Inhibit time EMCY", u16, rw, 0),
        _compound(0x1016, "Consumer heartbeat time", ObjectType.ARRAY, ro, consumers),
        _var(0x1017, "Producer heartbeat time", u16, rw, HEARTBEAT_MS),
        _compound(0x1018, "Identity object", ObjectType.RECORD, ro, [
            (1, "Vendor-ID", u32, ro, 0),
            (2, "Product code", u32, ro, product_code(board.program.name)),
            (3, "Revision number", u32, ro, board.progid),
            (4, "Serial number", u32, ro, board.serial)]),
        *_pdos(joint.node_id),
    ]


RPDO_MAPS = ((0x6040, 0x6060), (0x607A, 0x60FF))
"""Mapped objects (sub-index 0) of RPDO1 and RPDO2."""
TPDO_MAPS = ((0x6041, 0x6061), (0x6064, 0x606C))
"""Mapped objects of TPDO1 and TPDO2."""
_MAP_BITS = {0x6040: 16, 0x6060: 8, 0x607A: 32, 0x60FF: 32, 0x6041: 16, 0x6061: 8,
             0x6064: 32, 0x606C: 32}


def _pdos(node_id: int) -> list[Object]:
    u8, u16, u32, rw, ro = (DataType.UNSIGNED8, DataType.UNSIGNED16, DataType.UNSIGNED32,
                            Access.RW, Access.RO)
    out: list[Object] = []
    for receive, comm, maps, cob in ((True, 0x1400, RPDO_MAPS, 0x200),
                                     (False, 0x1800, TPDO_MAPS, 0x180)):
        what = "RPDO" if receive else "TPDO"
        for n in range(PDOS):
            mapped = maps[n] if n < len(maps) else ()
            cob_id = cob + 0x100 * n + node_id + (0 if mapped else 0x80000000)
            kind = 255 if receive or not mapped else 1
            subs = [(1, f"COB-ID used by {what}", u32, rw, cob_id),
                    (2, "Transmission type", u8, rw, kind)]
            if not receive:
                subs += [(3, "Inhibit time", u16, rw, 0), (5, "Event timer", u16, rw, 0),
                         (6, "SYNC start value", u8, rw, 0)]
            out.append(_compound(comm + n, f"{what}{n + 1} communication parameter",
                                 ObjectType.RECORD, ro, subs))
            entries = [(i + 1, f"Mapping entry {i + 1}", u32, rw,
                        (mapped[i] << 16 | _MAP_BITS[mapped[i]]) if i < len(mapped) else 0)
                       for i in range(MAP_ENTRIES)]
            record = _compound(comm + 0x200 + n, f"{what}{n + 1} mapping parameter",
                               ObjectType.RECORD, rw, entries)
            out.append(Object(record.index, record.name, record.object_type, (
                Entry(record.index, 0, "Number of mapped objects", u8, rw, len(mapped)),
                *record.entries[1:])))
    return sorted(out, key=lambda o: o.index)


def supported_modes(joint: Joint) -> SupportedModes:
    """PP, PV and CSP on every joint; HM where the axis homes on its own (a homing
    Command and Reset PWM of its own: armar3, not LAURON-IV's leg-wide Reference Run)."""
    modes = SupportedModes.PP | SupportedModes.PV | SupportedModes.CSP
    if joint.board.model.command_homing is not None and joint.edge(Role.RESET_PWM):
        modes |= SupportedModes.HM
    return modes


def _edge(joint: Joint, role: Role) -> BoardEdge:
    e = joint.edge(role)
    assert e is not None, role  # every AxisModel names these roles
    return e


def _cia402(joint: Joint) -> list[Object]:
    i8, i16, i32 = DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER32
    u16, u32 = DataType.UNSIGNED16, DataType.UNSIGNED32
    ro, rw = Access.RO, Access.RW
    target, target_vel = _edge(joint, Role.TARGET).spec, _edge(joint, Role.TARGET_VEL).spec
    low, high = _edge(joint, Role.MIN_POSITION), _edge(joint, Role.MAX_POSITION)
    vmax = _edge(joint, Role.MAX_VELOCITY)
    scale = joint.board.model.velocity_scale
    modes = supported_modes(joint)
    limits = Object(0x607D, "Software position limit", ObjectType.ARRAY, (
        Entry(0x607D, 0, "Highest sub-index supported", DataType.UNSIGNED8, ro, 2),
        Entry(0x607D, 1, "Min position limit", i32, rw, low.default, low.spec.minimum,
              low.spec.maximum),
        Entry(0x607D, 2, "Max position limit", i32, rw, high.default, high.spec.minimum,
              high.spec.maximum)))
    out = [
        _var(0x603F, "Error code", u16, ro, 0, pdo=True),
        _var(0x6040, "Controlword", u16, rw, 0, pdo=True),
        _var(0x6041, "Statusword", u16, ro, 0, pdo=True),
        _var(0x605A, "Quick stop option code", i16, rw, 2, low=0, high=8),
        _var(0x6060, "Modes of operation", i8, rw, 0, pdo=True),
        _var(0x6061, "Modes of operation display", i8, ro, 0, pdo=True),
        _var(0x605E, "Fault reaction option code", i16, rw, 0, low=0, high=0),
        _var(0x6064, "Position actual value", i32, ro, 0, pdo=True),
        _var(0x6065, "Following error window", u32, rw, _DRIVE.following_error_window),
        _var(0x6066, "Following error time out", u16, rw, _DRIVE.following_error_time_out),
        _var(0x6067, "Position window", u32, rw, POSITION_WINDOW),
        _var(0x6068, "Position window time", u16, rw, POSITION_WINDOW_MS),
        _var(0x606C, "Velocity actual value", i32, ro, 0, pdo=True),
        _var(0x606D, "Velocity window", u16, rw, _DRIVE.velocity_window),
        _var(0x606E, "Velocity window time", u16, rw, _DRIVE.velocity_window_time),
        _var(0x606F, "Velocity threshold", u16, rw, _DRIVE.velocity_threshold),
        _var(0x6070, "Velocity threshold time", u16, rw, _DRIVE.velocity_threshold_time),
        _var(0x607A, "Target position", i32, rw, 0, low=target.minimum,
             high=target.maximum, pdo=True),
        limits,
        _var(0x6081, "Profile velocity", u32, rw, max(0, vmax.default) * scale,
             low=max(0, vmax.spec.minimum) * scale, high=max(0, vmax.spec.maximum) * scale,
             pdo=True),
        _var(0x6083, "Profile acceleration", u32, rw, 0),
        _var(0x6084, "Profile deceleration", u32, rw, 0),
        _compound(0x60C2, "Interpolation time period", ObjectType.RECORD, ro, [
            (1, "Interpolation time period value", DataType.UNSIGNED8, rw, 10),
            (2, "Interpolation time index", i8, rw, -3)]),
        _var(0x60FF, "Target velocity", i32, rw, 0, low=target_vel.minimum,
             high=target_vel.maximum, pdo=True),
        _var(0x6502, "Supported drive modes", u32, ro, int(modes)),
    ]
    if SupportedModes.HM in modes:
        offset = _edge(joint, Role.RESET_OFFSET)
        out += [_var(0x607C, "Home offset", DataType.INTEGER32, rw, offset.default,
                     low=offset.spec.minimum, high=offset.spec.maximum),
                _var(0x6098, "Homing method", i8, rw, HOMING_METHOD, low=-4,
                     high=HOMING_METHOD),
                _compound(0x6099, "Homing speeds", ObjectType.ARRAY, ro, [
                    (1, "Speed during search for switch", u32, rw, 0),
                    (2, "Speed during search for zero", u32, rw, 0)])]
    return out


def _data_type(spec: EdgeSpec) -> DataType:
    if spec.width == 2:
        return DataType.INTEGER16 if spec.signed else DataType.UNSIGNED16
    return DataType.INTEGER32 if spec.signed else DataType.UNSIGNED32


def manufacturer_index(edge: BoardEdge) -> int:
    """Where an edge of the board is in the dictionary (0x2000 + PAR index ...)."""
    return MANUFACTURER_BASE[edge.kind] + edge.index


def _manufacturer(joint: Joint) -> list[Object]:
    out = []
    for e in joint.board.edges:
        if e.index >= MAX_EDGES:
            raise InputError(f"{joint.where}: {e.kind.name} edge {e.index} ('{e.unique}') "
                             f"does not fit the manufacturer objects (at most {MAX_EDGES} "
                             "per kind)", file=str(joint.board.tree), line=e.line or None)
        access = Access.RO if e.kind is EdgeKind.SO else Access.RW
        out.append(_var(manufacturer_index(e), e.unique, _data_type(e.spec), access,
                        e.default, low=e.spec.minimum, high=e.spec.maximum,
                        pdo=e.kind is not EdgeKind.PAR))
    return out


def product_code(program: str) -> int:
    """0x1018 product code of a program's joints: the CRC-32 of its name."""
    return zlib.crc32(program.encode())


def _check_text(joint: Joint, objects: list[Object]) -> None:
    """Every name fits an EDS line: printable ASCII without ``;`` or ``#`` (which Lely and
    canopen take for a comment); InputError naming the tree line."""
    for o in objects:
        for name in (o.name, *(e.name for e in o.entries)):
            bad = [c for c in name if not " " <= c <= "~" or c in ";#"]
            if bad or name != name.strip():
                line = next((b.line for b in joint.board.edges if b.unique == name), 0)
                raise InputError(f"'{name}' ({joint.where}) cannot be written to an EDS: "
                                 "names there are printable ASCII without ';' and '#' and "
                                 "without blanks at either end", file=str(joint.board.tree),
                                 line=line or None)


def build(joint: Joint) -> Dictionary:
    """The object dictionary of ``joint``'s node; InputError for a name an EDS cannot
    hold (naming its tree line)."""
    board = joint.board
    objects = sorted(_communication(joint) + _cia402(joint) + _manufacturer(joint),
                     key=lambda o: o.index)
    _check_text(joint, objects)
    device = DeviceInfo(vendor_name="ucom-tools", vendor_number=0,
                        product_name=board.program.name,
                        product_number=product_code(board.program.name),
                        revision_number=board.progid)
    description = (f"{joint.name}: axis {joint.letter} of {board.where}, "
                   f"{board.program.name}, as a CiA 402 drive (ucom gateway)")
    return Dictionary(joint.name, joint.key, joint.node_id, description, device,
                      tuple(objects))


def to_canopen(dictionary: Dictionary) -> ObjectDictionary:
    """canopen's ObjectDictionary of ``dictionary``: what canopen's ``import_od`` of its
    EDS (:mod:`ucom_tools.gateway.eds`) with its node ID gives, for ``LocalNode``."""
    od = ObjectDictionary()
    od.node_id = dictionary.node_id
    d = dictionary.device
    info = od.device_information
    info.vendor_name, info.vendor_number = d.vendor_name, d.vendor_number
    info.product_name, info.product_number = d.product_name, d.product_number
    info.revision_number, info.order_code = d.revision_number, ""
    info.simple_boot_up_master, info.simple_boot_up_slave = False, d.simple_boot_up_slave
    info.granularity = d.granularity
    info.dynamic_channels_supported, info.group_messaging = False, False
    # canopen annotates these as bool; its import sets the numbers
    info.nr_of_RXPDO = d.nr_rxpdo  # type: ignore[assignment]
    info.nr_of_TXPDO = d.nr_txpdo  # type: ignore[assignment]
    info.LSS_supported = False
    info.allowed_baudrates = {k * 1000 for k in BAUD_RATES_KBIT}
    for dt in d.dummies:  # as canopen's import makes them of [DummyUsage]
        dummy = ODVariable(f"Dummy{int(dt):04d}", int(dt), 0)
        dummy.data_type, dummy.access_type = int(dt), "const"
        od.add_object(dummy)
    for o in dictionary.objects:
        if o.object_type is ObjectType.VAR:
            od.add_object(_variable(o.entries[0]))
            continue
        compound = ODArray(o.name, o.index) if o.object_type is ObjectType.ARRAY \
            else ODRecord(o.name, o.index)
        for e in o.entries:
            compound.add_member(_variable(e))
        od.add_object(compound)
    return od


BAUD_RATES_KBIT = (10, 20, 50, 125, 250, 500, 800, 1000)
"""The bit rates [kbit/s] the EDS says the node takes: every one (the gateway's CANopen
bus is whatever python-can bus it is given)."""


def _variable(e: Entry) -> ODVariable:
    var = ODVariable(e.name, e.index, e.subindex)
    var.data_type = int(e.data_type)
    var.access_type = e.access.value
    var.pdo_mappable = e.pdo_mappable
    var.min, var.max = e.low, e.high
    var.default = e.default  # type: ignore[assignment]  # a str: VISIBLE_STRING
    return var
