"""ElementSplitter.plain_data, the receiving path's scan byte by byte (compiled) or its
regular expressions (from source), takes what the regular expressions took: the same
elements (and stops where they stopped), the same identifiers, data and time stamps (bit
for bit), the same offset.  Each check runs both ways (``_scanned``, ``_matched``) and
``plain_data`` itself, on either build.

The reference is the former implementation, kept here: a match of ``_STD_RUN``, then
``_FRAME_FIELDS.findall`` over it and :func:`seconds_of` per frame.  Each case feeds the
same bytes to a splitter and to the reference, after an element that ``next`` takes first
(so that the run does not start at the buffer's start) or without it; the cases are the
usual elements, every boundary of the form, every cut of a run, runs longer than the
copy's window, and some tens of thousands of mutated runs (seeded, and hypothesis').
"""

from __future__ import annotations

import binascii
import math
import random
import re
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ucom_tools.wire import socketcand as wire
from ucom_tools.wire.socketcand import (
    MAX_ELEMENT,
    ElementSplitter,
    frame_element,
    seconds_of,
)

_STD_RUN = re.compile(rb"(?:< frame [0-7][0-9A-Fa-f]{2} "
                      rb"\d{1,20}\.\d{1,15} (?:[0-9A-Fa-f]{2}){0,8} ?>)+")
_FRAME_FIELDS = re.compile(rb"< frame ([0-9A-Fa-f]+) (\d+)\.(\d+) ([0-9A-Fa-f]*) ?>")
_FRAME_RUN_LONGEST = 80

LEAD = b"< echo >"
"""An element that next() takes before plain_data runs (the run then starts at 8)."""

Frames = list[tuple[int, bytes, float]]


def reference(buf: bytes, pos: int, limit: int, arrival: float, offset: float,
              ) -> tuple[Frames, float, int]:
    """plain_data as it was (commit e0d8f26): the frames, the offset and where the
    splitter's unread part starts after it."""
    if limit <= _FRAME_RUN_LONGEST:
        return [], offset, pos
    run = _STD_RUN.match(buf, pos)
    if run is None:
        return [], offset, pos
    end = run.end()
    out: Frames = []
    for ident, seconds, fraction, data in _FRAME_FIELDS.findall(buf, pos, end):
        stamp = seconds_of(seconds, fraction)
        if arrival - stamp < offset:
            offset = arrival - stamp
        out.append((int(ident, 16), binascii.unhexlify(data), stamp + offset))
    return out, offset, end


def bits(x: float) -> bytes:
    return struct.pack("<d", x)


def exact(frames: Frames, offset: float) -> tuple[object, ...]:
    """The frames and the offset with the types and the floats' bits (== on floats would
    take -0.0 for 0.0)."""
    return tuple((type(i), i, type(d), d, bits(t)) for i, d, t in frames), bits(offset)


def check(buf: bytes, arrival: float = 1764654321.5, offset: float = math.inf, *,
          lead: bool = False, limit: int = MAX_ELEMENT) -> Frames:
    """plain_data of ``buf`` (after LEAD, taken by next(), if ``lead``) is the
    reference's, and leaves the unread part where the reference's run ended; its frames."""
    splitter = ElementSplitter(limit=limit)
    pos = 0
    if lead:
        splitter.feed(LEAD)
        pos = len(LEAD)
    splitter.feed(buf)
    if lead:
        assert splitter.next() == LEAD[1:-1]
    text = LEAD + buf if lead else buf
    want, want_offset, end = reference(text, pos, limit, arrival, offset)
    if limit > _FRAME_RUN_LONGEST:  # both ways, whichever plain_data takes (_NATIVE)
        for way in (wire._scanned, wire._matched):
            frames, way_offset, way_end = way(bytearray(text), pos, arrival, offset)
            assert (exact(frames, way_offset), way_end) == (exact(want, want_offset), end), \
                (way, buf)
    got, got_offset = splitter.plain_data(arrival, offset)
    assert exact(got, got_offset) == exact(want, want_offset), buf
    assert splitter.unread() == len(text) - end, buf
    return got


def check_both(buf: bytes, arrival: float = 1764654321.5, offset: float = math.inf,
               ) -> Frames:
    got = check(buf, arrival, offset)
    check(buf, arrival, offset, lead=True)
    return got


def frame(ident: bytes = b"38A", stamp: bytes = b"1764654321.123456",
          data: bytes = b"0011223344556677", tail: bytes = b" >") -> bytes:
    return b"< frame " + ident + b" " + stamp + b" " + data + tail


GOOD = frame()
NEXT = frame(b"1A2", b"1764654321.123789", b"AABB")


# ---------------------------------------------------------------------- usual elements
def test_the_usual_elements() -> None:
    run = b"".join(frame_element(ident, 1764654321.123456 + 1e-4 * k, bytes(range(n)))
                   for k, (ident, n) in enumerate(
                       [(0x3A1, 8), (0x3A2, 8), (0x3A3, 8), (0x3A4, 4), (0x000, 0),
                        (0x7FF, 1), (0x123, 5), (0x1, 2)]))
    got = check_both(run)
    assert [(i, d) for i, d, _ in got] == [
        (0x3A1, bytes(range(8))), (0x3A2, bytes(range(8))), (0x3A3, bytes(range(8))),
        (0x3A4, bytes(range(4))), (0, b""), (0x7FF, b"\x00"), (0x123, bytes(range(5))),
        (0x1, b"\x00\x01")]
    for arrival, offset in ((1764654321.5, math.inf), (1764654321.5, 0.25),
                            (0.0, math.inf), (1764654321.0, -1e-3), (2e9, 0.0)):
        check_both(run, arrival, offset)
    check_both(run + b"< echo >" + run)  # stops at the other element
    check_both(b"")
    check_both(b"< echo >" + run)


def test_the_offset_is_the_smallest_difference_so_far() -> None:
    """Frame by frame: a frame's time stamp is on the clock the frames before it set."""
    run = frame(stamp=b"100.5") + frame(stamp=b"100.25") + frame(stamp=b"101.0")
    got = check(run, arrival=102.0, offset=math.inf)
    assert [t for _, _, t in got] == [100.5 + 1.5, 100.25 + 1.5, 101.0 + 1.0]
    splitter = ElementSplitter()
    splitter.feed(run)
    assert splitter.plain_data(102.0, math.inf)[1] == 1.0
    splitter.feed(run)
    assert splitter.plain_data(102.0, 0.5) == ([(0x38A, bytes.fromhex("0011223344556677"),
                                                 t + 0.5) for t in (100.5, 100.25, 101.0)], 0.5)


# ---------------------------------------------------------------------- boundaries
BOUNDARIES = {
    # data
    "no data": frame(data=b"", tail=b">"),
    "no data, two blanks": frame(data=b"", tail=b" >"),
    "no data, three blanks": frame(data=b"", tail=b"  >"),
    "no data, no blank": b"< frame 38A 1.5>",
    "8 bytes": frame(data=b"0123456789abcdef"),
    "8 bytes no blank": frame(data=b"0123456789ABCDEF", tail=b">"),
    "9 bytes": frame(data=b"00112233445566778F"),
    "1 digit": frame(data=b"0"),
    "3 digits": frame(data=b"012"),
    "15 digits": frame(data=b"0" * 15),
    "17 digits": frame(data=b"0" * 17),
    "17 digits no blank": frame(data=b"0" * 17, tail=b">"),
    "mixed case data": frame(data=b"aBcDeF09"),
    "blank inside data": frame(data=b"00 11"),
    "not hex data": frame(data=b"0g"),
    "two blanks after data": frame(data=b"0011", tail=b"  >"),
    "tab after data": frame(data=b"0011", tail=b"\t>"),
    # identifier
    "7FF": frame(b"7FF"),
    "7ff": frame(b"7ff"),
    "000": frame(b"000"),
    "800": frame(b"800"),
    "8FF": frame(b"8FF"),
    "fff": frame(b"fff"),
    "lower-case": frame(b"3ab"),
    "mixed-case": frame(b"3aB"),
    "2 digits": frame(b"7F"),
    "4 digits": frame(b"07FF"),
    "8 digits (extended)": frame(b"00000123"),
    "8 digits over 29 bits": frame(b"FFFFFFFF"),
    "not hex identifier": frame(b"1G2"),
    # time stamp
    "1 second digit": frame(stamp=b"1.5"),
    "20 second digits": frame(stamp=b"9" * 20 + b".5"),
    "21 second digits": frame(stamp=b"9" * 21 + b".5"),
    "20 second digits, leading zeros": frame(stamp=b"0" * 19 + b"1.5"),
    "21 second digits, leading zeros": frame(stamp=b"0" * 20 + b"1.5"),
    "15 fraction digits": frame(stamp=b"1." + b"1" * 15),
    "16 fraction digits": frame(stamp=b"1." + b"1" * 16),
    "15 fraction digits, long seconds": frame(stamp=b"9" * 20 + b"." + b"9" * 15),
    "no second digits": frame(stamp=b".5"),
    "no fraction digits": frame(stamp=b"1."),
    "no point": frame(stamp=b"1764654321"),
    "two points": frame(stamp=b"1.5.5"),
    "exponent": frame(stamp=b"1.5e3"),
    "sign": frame(stamp=b"+1.5"),
    "minus": frame(stamp=b"-1.5"),
    "underscore": frame(stamp=b"1_000.5"),
    "non-ASCII digit": frame(stamp=b"1\xd9\xa3.5"),
    "digits = 2**53": frame(stamp=b"9007199254.740992"),
    "digits = 2**53 + 1": frame(stamp=b"9007199254.740993"),
    "digits = 2**53 + 1, 18 of them": frame(stamp=b"90071992547409.9300"),
    "18 digits": frame(stamp=b"123456789012.345678"),
    "19 digits": frame(stamp=b"1234567890123.456789"),
    "19 digits, small": frame(stamp=b"0000000000001.000001"),
    "nanoseconds": frame(stamp=b"1764654321.123456789"),
    "zero": frame(stamp=b"0.0"),
    # blanks and brackets
    "no blank after frame": b"< frame38A 1.5 00 >",
    "no blank after identifier": b"< frame 38A1.5 00 >",
    "no blank after stamp": b"< frame 38A 1.5AB >",
    "no blank after stamp, digits": b"< frame 38A 1.500 >",
    "no blank after <": b"<frame 38A 1.5 00 >",
    "two blanks after <": b"<  frame 38A 1.5 00 >",
    "two blanks after frame": b"< frame  38A 1.5 00 >",
    "two blanks after identifier": b"< frame 38A  1.5 00 >",
    "two blanks after stamp": b"< frame 38A 1.5  00 >",
    "tab for a blank": b"< frame\t38A 1.5 00 >",
    "FRAME": b"< FRAME 38A 1.5 00 >",
    "no >": frame(tail=b" "),
    "no > and a new element": frame(tail=b" ") + NEXT,
    "< inside": frame(tail=b" <>"),
    "> early": b"< frame 38A 1.5> 00 >",
    "the shortest": b"< frame 000 0.0 >",
    "the longest": frame(b"7ff", b"9" * 20 + b"." + b"9" * 15, b"f" * 16),
    "the longest and one more": frame(b"7ff", b"9" * 20 + b"." + b"9" * 15, b"f" * 16,
                                      b"  >"),
}


@pytest.mark.parametrize("element", list(BOUNDARIES.values()), ids=list(BOUNDARIES))
def test_every_boundary(element: bytes) -> None:
    """Each alone, between usual elements, first and last; and each cut short."""
    for buf in (element, GOOD + element + NEXT, element + GOOD, GOOD + element,
                GOOD + element + b"junk" + GOOD):
        check_both(buf)
    for cut in range(len(element)):
        check_both(GOOD + element[:cut])


def test_the_boundaries_read_as_meant() -> None:
    """What the reference takes of some of them (so that the cases test what they say)."""
    def taken(name: str) -> int:
        return len(check(BOUNDARIES[name] + NEXT))
    for name in ("no data", "no data, two blanks", "8 bytes", "8 bytes no blank",
                 "7FF", "7ff", "lower-case", "20 second digits", "15 fraction digits",
                 "the longest", "digits = 2**53 + 1", "19 digits", "nanoseconds"):
        assert taken(name) == 2, name
    for name in ("no data, three blanks", "no data, no blank", "9 bytes", "1 digit",
                 "3 digits", "17 digits", "800", "8 digits (extended)", "21 second digits",
                 "16 fraction digits", "no blank after stamp", "two blanks after stamp",
                 "no >", "the longest and one more", "underscore", "sign"):
        assert taken(name) == 0, name
    assert len(BOUNDARIES["the longest"]) == wire._STD_LONGEST


def test_junk_and_other_elements_stop_the_run() -> None:
    for between in (b" ", b"x", b">", b"<", b"\n", b"< echo >", b"< ok >",
                    frame(b"00000123"), b"< error 1 2.5 >", b"< frame 38A 1.5 00 ",
                    b"< frame >", b"< >"):
        check_both(GOOD + NEXT + between + GOOD)
        check_both(between + GOOD)


def test_a_short_limit_takes_nothing() -> None:
    run = GOOD + NEXT
    for limit in (16, 67, 79, 80):
        assert check(run, limit=limit) == []
        check(run, limit=limit, lead=True)
    for limit in (81, 100, MAX_ELEMENT):
        assert len(check(run, limit=limit)) == 2
        check(run, limit=limit, lead=True)


def test_every_cut_of_a_run() -> None:
    """An unfinished element at the end of the buffer is not taken; what comes before
    it is."""
    run = b"".join(frame(b"%03X" % (0x111 * k % 0x800), b"%d.%06d" % (1764654321 + k, k),
                         b"%02X" % k * (k % 9), b" >" if k % 2 else b">")
                   for k in range(12))
    for cut in range(len(run) + 1):
        check_both(run[:cut])


# ---------------------------------------------------------------------- long runs
def sized(n: int) -> bytes:
    """A frame element in the usual form of ``n`` bytes (17..67)."""
    rest = n - len(b"< frame 000 . >")
    seconds = min(20, rest - 1)
    rest -= seconds
    places = min(15, rest)
    rest -= places
    tail = b" >" if rest % 2 else b">"
    element = frame(b"000", b"1" * seconds + b"." + b"2" * places, b"3" * (rest & ~1), tail)
    assert len(element) == n
    return element


def filler(n: int) -> bytes:
    """Frame elements in the usual form of ``n`` bytes together (``n`` >= 17)."""
    out = b""
    while n > wire._STD_LONGEST:
        size = min(wire._STD_LONGEST, n - 17)
        out += sized(size)
        n -= size
    return out + sized(n)


def test_sized_elements() -> None:
    for n in range(17, wire._STD_LONGEST + 1):
        assert len(check(sized(n))) == 1


def test_runs_longer_than_the_window() -> None:
    """The buffer is read a window at a time: runs that end, stop or go on at every
    place near its edges."""
    window = wire._STD_WINDOW
    rng = random.Random(5)
    body = b""
    while len(body) < window - 2 * wire._STD_LONGEST:
        body += random_element(rng, valid=True)
    more = b"".join(random_element(rng, valid=True) for _ in range(200))
    for end in range(window - wire._STD_LONGEST - 8, window + wire._STD_LONGEST + 16):
        head = body + filler(end - len(body))
        assert len(head) == end
        for after in (b"", more, b"x" + more, b"< echo >" + more, GOOD[:-1],
                      GOOD[:-1] + b"x" + more, frame(b"00000123") + more):
            got = check_both(head + after)
            assert len(got) >= body.count(b"<")
    long_run = b"".join(random_element(rng, valid=True) for _ in range(400))
    assert len(long_run) > 3 * window
    assert len(check_both(long_run)) == 400
    for at in rng.sample(range(len(long_run)), 100):
        check_both(long_run[:at] + b"x" + long_run[at:])


# ---------------------------------------------------------------------- fuzz
HEX = b"0123456789ABCDEFabcdef"
ODD = b"<> .0123456789abcdefABCDEFgG\t\n\x00\xff+-_e"


def digits(rng: random.Random, n: int) -> bytes:
    kind = rng.random()
    if kind < 0.1:
        return b"9" * n
    if kind < 0.2:
        return b"0" * n
    if kind < 0.3 and n > 1:
        return b"0" * (n - 1) + b"1"
    return bytes(rng.choice(b"0123456789") for _ in range(n))


def random_element(rng: random.Random, valid: bool = False) -> bytes:
    """A frame element near the usual form: with ``valid``, in it."""
    r = rng.random()
    if valid or r < 0.7:
        ident = b"%03X" % rng.randrange(0x800)
        if rng.random() < 0.3:
            ident = ident.lower()
    elif r < 0.8:
        ident = b"%03X" % rng.randrange(0x800, 0x1000)
    elif r < 0.9:
        ident = b"%08X" % rng.randrange(1 << 29)
    else:
        ident = bytes(rng.choice(HEX) for _ in range(rng.choice((1, 2, 4, 7, 9))))
    if valid:
        secs, places = rng.choice((10, 10, 10, 1, 5, 19, 20)), rng.choice((6, 6, 1, 9, 15))
        size = 2 * rng.randrange(9)
    else:
        secs = rng.choice((10, 10, 10, 1, 2, 9, 12, 13, 18, 19, 20, 20, 21, 22, 0))
        places = rng.choice((6, 6, 6, 1, 3, 8, 9, 14, 15, 15, 16, 0))
        size = rng.choice((0, 2, 4, 6, 8, 10, 12, 14, 16, 16, 16, 1, 3, 15, 17, 18))
    stamp = digits(rng, secs) + b"." + digits(rng, places)
    if rng.random() < 0.05:
        stamp = b"%.6f" % (rng.random() * 2e9)
    data = bytes(rng.choice(HEX) for _ in range(size))
    tail = rng.choice((b" >", b" >", b">")) if valid else rng.choice(
        (b" >", b" >", b" >", b">", b"  >", b" "))
    return frame(ident, stamp, data, tail)


def mutate(rng: random.Random, buf: bytes) -> bytes:
    b = bytearray(buf)
    for _ in range(rng.choice((0, 1, 1, 1, 2, 3))):
        at = rng.randrange(len(b) + 1)
        byte = rng.choice(ODD) if rng.random() < 0.8 else rng.randrange(256)
        what = rng.random()
        if what < 0.35:
            b.insert(at, byte)
        elif what < 0.7 and at < len(b):
            del b[at]
        elif at < len(b):
            b[at] = byte
    return bytes(b)


def test_fuzz_seeded() -> None:
    """Runs of elements near the usual form, bytes inserted, deleted and replaced."""
    rng = random.Random(20261202)
    taken = 0
    for case in range(30000):
        run = b"".join(random_element(rng, valid=rng.random() < 0.75)
                       for _ in range(rng.randrange(1, 6)))
        if rng.random() < 0.1:
            run += rng.choice((b"< echo >", b"< frame 38A 1.5 00", b"junk"))
        buf = mutate(rng, run)
        arrival = rng.choice((1764654321.5, 0.0, 1e20, rng.random() * 2e9))
        offset = rng.choice((math.inf, 0.0, -1.0, rng.random()))
        taken += len(check(buf, arrival, offset, lead=case % 3 == 0))
    assert taken > 25000, taken  # most runs are mostly elements that are taken


def tokens() -> st.SearchStrategy[bytes]:
    """Pieces of frame elements, to be put together any way."""
    return st.one_of(
        st.sampled_from([b"< frame ", b"<", b">", b" >", b" ", b".", b"  ", b"< echo >",
                         b"frame", b"\x00", b"\xff", b"-", b"_"]),
        st.integers(0, 0xFFF).map(lambda v: b"%03X" % v),
        st.integers(0, 0xFFF).map(lambda v: b"%03x" % v),
        st.integers(0, 10 ** 22).map(lambda v: b"%d" % v),
        st.integers(1, 22).map(lambda n: b"0" * n),
        st.binary(max_size=9).map(lambda d: binascii.hexlify(d)),
        st.binary(max_size=9).map(lambda d: binascii.hexlify(d)[1:]),
        st.builds(lambda i, s, f, d, t: frame(b"%03X" % i, b"%d.%s" % (s, f), d, t),
                  st.integers(0, 0x7FF), st.integers(0, 10 ** 20),
                  st.integers(1, 16).map(lambda n: b"1" * n),
                  st.binary(max_size=9).map(lambda d: binascii.hexlify(d)),
                  st.sampled_from([b" >", b">", b"  >"])),
    )


@settings(max_examples=1000, deadline=None)
@given(st.lists(tokens(), max_size=24).map(b"".join),
       st.sampled_from([1764654321.5, 0.0, 1e25]), st.sampled_from([math.inf, 0.0, 0.5]),
       st.booleans())
def test_fuzz_tokens(buf: bytes, arrival: float, offset: float, lead: bool) -> None:
    check(buf, arrival, offset, lead=lead)
