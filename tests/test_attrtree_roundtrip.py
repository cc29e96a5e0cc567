"""Property tests: generated trees survive write -> parse unchanged, whatever the layout."""

from __future__ import annotations

import string
from dataclasses import replace

from hypothesis import given, settings
from hypothesis import strategies as st

from ucom_tools.config.attrtree import (
    KIND_ORDER,
    BoardBlock,
    ChangeKind,
    Edge,
    Tree,
    TreeEdgeKind,
    Value,
    diff,
    dumps,
    parse,
)

NAME_CHARS = string.ascii_letters + string.digits + " \t()[]-_.,/%#=>'\"+*äöüßÄµ°€"
FIRST = NAME_CHARS.replace(" ", "").replace("\t", "").replace("#", "")
LAST = NAME_CHARS.replace(" ", "").replace("\t", "")


def _no_arrow(s: str) -> str:
    while "==>" in s:
        s = s.replace("==>", "=>")
    return s


names = st.one_of(
    st.sampled_from(FIRST),
    st.builds(lambda a, mid, z: _no_arrow(a + mid + z), st.sampled_from(FIRST),
              st.text(NAME_CHARS, max_size=20), st.sampled_from(LAST)),
)
"""Valid names: no blank or tab at either end, no '#' first, no ':', '{', '}' or '==>'."""


def distinct(n: int) -> st.SearchStrategy[list[str]]:
    """n different names (a repeated one gets its position appended)."""
    def dedupe(xs: list[str]) -> list[str]:
        seen: set[str] = set()
        out = []
        for i, x in enumerate(xs):
            x = x if x not in seen else f"{x} {i}"
            seen.add(x)
            out.append(x)
        return out
    return st.lists(names, min_size=n, max_size=n).map(dedupe)


value_texts = st.one_of(
    st.integers(-(10 ** 12), 10 ** 12).map(str),
    st.integers(0, 2 ** 64).map(lambda n: f"0x{n:x}"),
    st.integers(0, 2 ** 16).map(lambda n: f"-0x{n:X}"),
    st.floats(allow_nan=False, allow_infinity=False, width=64).map(lambda x: Value.of(x).text),
    st.from_regex(r"-?[0-9]{1,6}\.[0-9]{1,6}", fullmatch=True),
    st.from_regex(r"0[0-9]{1,4}", fullmatch=True),
)


@st.composite
def boards(draw: st.DrawFn, number: int, prefix: str) -> BoardBlock:
    n = draw(st.integers(1, 20))
    kinds = sorted(draw(st.lists(st.sampled_from(KIND_ORDER), min_size=n, max_size=n)),
                   key=KIND_ORDER.index)
    generic = draw(distinct(n))
    unique = draw(distinct(n))
    edges = []
    for i, kind in enumerate(kinds):
        default = None
        if kind is not TreeEdgeKind.SO and draw(st.booleans()):
            default = Value.parse(draw(value_texts))
        edges.append(Edge(i, kind, generic[i], unique[i], default))
    return BoardBlock(number, prefix, tuple(edges))


@st.composite
def trees(draw: st.DrawFn) -> Tree:
    k = draw(st.integers(1, 3))
    numbers = draw(st.lists(st.integers(0, 10 ** 6), min_size=k, max_size=k, unique=True))
    prefixes = draw(distinct(k))
    return Tree(tuple(draw(boards(n, p)) for n, p in zip(numbers, prefixes, strict=True)))


@settings(max_examples=200, deadline=None)
@given(trees())
def test_write_then_parse_gives_the_same_tree(tree: Tree) -> None:
    text = dumps(tree)
    again = parse(text, "gen")
    assert again == tree
    assert dumps(again) == text
    assert diff(tree, again) == ()


@st.composite
def messy(draw: st.DrawFn, text: str) -> str:
    """The same tree written by a careless hand: indentation and trailing blanks and tabs,
    blank lines and ordinary comments anywhere, 'Name {' for 'Name{', CR LF line ends."""
    ws = st.text(" \t", max_size=3)
    out = []
    for line in text.split("\n")[:-1]:
        for _ in range(draw(st.integers(0, 2))):
            out.append(draw(st.sampled_from([
                "", draw(ws), "#", "# CIA", "#  remark: x{", "#}DSP", "# PAR x"])))
        body = line.strip(" ")
        if body.endswith("{") and draw(st.booleans()):
            body = body[:-1] + draw(ws) + "{"
        out.append(draw(ws) + body + draw(ws))
    eol = draw(st.sampled_from(["\n", "\r\n"]))
    return eol.join(out) + draw(st.sampled_from(["", eol]))


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_layout_and_comments_do_not_change_the_tree(data: st.DataObject) -> None:
    tree = data.draw(trees())
    assert parse(data.draw(messy(dumps(tree))).encode("utf-8"), "messy") == tree


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_diff_names_exactly_the_one_change(data: st.DataObject) -> None:
    a = data.draw(trees())
    assert diff(a, parse(dumps(a), "copy")) == ()
    bi = data.draw(st.integers(0, len(a.boards) - 1))
    board = a.boards[bi]
    ei = data.draw(st.integers(0, len(board.edges) - 1))
    edge = board.edges[ei]
    what = data.draw(st.sampled_from(list(ChangeKind)))
    edges = list(board.edges)
    boards = list(a.boards)
    if what is ChangeKind.RENAMED:
        edges[ei] = replace(edge, unique=edge.unique + " new")
    elif what is ChangeKind.GENERIC_CHANGED:
        edges[ei] = replace(edge, generic=edge.generic + " new")
    elif what is ChangeKind.KIND_CHANGED:
        so = edge.kind is TreeEdgeKind.SO
        edges[ei] = replace(edge, kind=TreeEdgeKind.CI if so else TreeEdgeKind.SO,
                            default=edge.default if so else None)
        if edge.default is not None:
            what = ChangeKind.KIND_CHANGED  # and default-removed, checked below
    elif what is ChangeKind.DEFAULT_CHANGED:
        old = edge.default.text if edge.default else None
        edges[ei] = replace(edge, default=Value.parse("-1" if old == "1" else "1"))
        what = ChangeKind.DEFAULT_ADDED if old is None else what
    elif what is ChangeKind.DEFAULT_ADDED or what is ChangeKind.DEFAULT_REMOVED:
        edges[ei] = replace(edge, default=None if edge.default else Value.parse("0x1"))
        what = ChangeKind.DEFAULT_REMOVED if edge.default else ChangeKind.DEFAULT_ADDED
    elif what is ChangeKind.EDGE_ADDED:
        edges.append(Edge(len(edges), TreeEdgeKind.PAR, "added g", "added u"))
        ei = len(edges) - 1
    elif what is ChangeKind.EDGE_REMOVED:
        edges.pop()
        ei = len(edges)
    elif what is ChangeKind.PREFIX_CHANGED:
        board = replace(board, prefix=board.prefix + " new")
    elif what is ChangeKind.BOARD_ADDED:
        boards.append(BoardBlock(max(a.numbers) + 1, "added", board.edges))
    elif what is ChangeKind.BOARD_REMOVED:
        if len(boards) == 1:
            return
        del boards[bi]
    if what not in (ChangeKind.BOARD_ADDED, ChangeKind.BOARD_REMOVED):
        boards[bi] = replace(board, edges=tuple(edges))
    changes = diff(a, Tree(tuple(boards)))
    assert changes and changes[0].kind is what
    assert all(c.board == (boards[-1].number if what is ChangeKind.BOARD_ADDED else
                           board.number) for c in changes)
    if (what is ChangeKind.KIND_CHANGED and edge.default is not None
            and edge.kind is not TreeEdgeKind.SO):
        assert [c.kind for c in changes] == [what, ChangeKind.DEFAULT_REMOVED]
    else:
        assert len(changes) == 1
    if changes[0].index is not None:
        assert changes[0].index == ei


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_value_of_keeps_the_number(x: float) -> None:
    v = Value.of(x)
    assert v.number == x and Value.parse(v.text) == v
