"""The init chain (B.2.2, Abb. B.3) and its LEDs (B.2.3), on correct and faulty wiring."""

from __future__ import annotations

from tests.conftest import chain_topology
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire.codes import StatusOp
from ucom_tools.wire.ids import seq


def leds(board) -> tuple[str, str, str]:
    d = board.leds()
    return d["red"], d["yellow"], d["green"]


def test_power_on_leds_first_yellow_only_others_yellow_and_green(host) -> None:
    h = host("armar3", "CAN1")
    assert [leds(b) for b in h.boards] == [
        ("off", "on", "off"), ("off", "on", "on"), ("off", "on", "on")]


def test_init_numbers_boards_in_chain_order(host) -> None:
    h = host("armar3", "CAN0")
    result = h.client.init_chain()
    assert [a.seq_id for a in result.acks] == [1, 2, 3]
    assert [a.serial for a in result.acks] == [b.identity.serial for b in h.boards]
    assert result.duplicates() == {}
    assert [b.seq_id for b in h.boards] == [1, 2, 3]
    # after the chain completed every init output is released: LEDs dark
    assert [leds(b) for b in h.boards] == [("off", "off", "off")] * 3


def test_init_of_31_boards(host) -> None:
    h = host(chain_topology(31))
    result = h.client.init_chain()
    assert [a.seq_id for a in result.acks] == list(range(1, 32))
    assert [b.seq_id for b in h.boards] == list(range(1, 32))


def test_broken_init_line_gives_two_chains(host) -> None:
    h = host(chain_topology(5, extra={2: 'init_link = "broken"'}))
    result = h.client.init_chain()
    dup = result.duplicates()
    serials = [b.identity.serial for b in h.boards]
    assert {n: {a.serial for a in acks} for n, acks in dup.items()} == {
        1: {serials[0], serials[2]}, 2: {serials[1], serials[3]}}
    assert [b.seq_id for b in h.boards] == [1, 2, 1, 2, 3]
    firsts = h.client.probe()
    assert sorted(a.serial for a in firsts) == sorted([serials[0], serials[2]])
    lasts = h.client.probe(last=True)
    assert sorted(a.serial for a in lasts) == sorted([serials[1], serials[4]])


def test_power_on_leds_show_a_broken_line(host) -> None:
    h = host(chain_topology(4, extra={2: 'init_link = "broken"'}))
    assert [leds(b)[2] for b in h.boards] == ["off", "on", "off", "on"]


def test_unpowered_board_splits_the_chain(host) -> None:
    h = host(chain_topology(5, extra={2: "powered = false"}))
    assert leds(h.boards[2]) == ("off", "off", "off")
    assert leds(h.boards[3]) == ("off", "on", "off")  # looks like a first board
    result = h.client.init_chain()
    assert len({a.serial for a in result.acks}) == 4
    assert set(result.duplicates()) == {1, 2}


def test_duplicate_fixed_ids_are_reported(host) -> None:
    h = host(chain_topology(3, extra={0: "fixed_id = 7", 2: "fixed_id = 7"}))
    result = h.client.init_chain()
    clashes = result.fixed_id_clashes()
    assert list(clashes) == [7]
    assert sorted(a.seq_id for a in clashes[7]) == [1, 3]


def test_probe_first_and_last_on_a_correct_chain(host) -> None:
    h = host("lauron4")
    serials = [b.identity.serial for b in h.boards]
    assert [a.serial for a in h.client.probe()] == [serials[0]]
    assert [a.serial for a in h.client.probe(last=True)] == [serials[-1]]
    # probes work before init: the answer carries no seq ID yet
    assert h.client.probe()[0].seq_id == 0


def test_set_init_pins_for_debugging(host) -> None:
    h = host("armar3", "CAN0")
    h.client.init_chain()
    h.client.set_status(seq(2), StatusOp.INIT_OUT, 1)
    assert leds(h.boards[1]) == ("off", "on", "off")
    assert leds(h.boards[2])[2] == "on"  # successor sees the set line
    h.client.set_status(seq(2), StatusOp.INIT_IN, 1)
    assert leds(h.boards[1]) == ("on", "on", "on")
    assert leds(h.boards[0]) == ("off", "off", "off")  # board 1 output line is pulled by 2
    assert h.boards[0].pins()["out_set"]
    status = h.client.status(seq(2))
    assert status.pins & 0b0101 == 0b0101 and status.leds & 0b111 == 0b111


def test_seq_id_can_be_changed(host) -> None:
    h = host("armar3", "CAN0")
    h.client.init_chain()
    replies = h.client.set_status(seq(3), StatusOp.SEQ_ID, 9)
    assert replies and replies[0].ok
    assert h.client.info(seq(9)).serial == h.boards[2].identity.serial


def test_kairo2_fleet_has_alternating_modules(host) -> None:
    fleet = Fleet.load("kairo2")
    kinds = [b.identity.board for b in fleet.boards["CAN0"]]
    assert kinds.count("KairoAlpha") == 6 and kinds.count("KairoGamma") == 5
    h = host(fleet)
    assert len(h.client.init_chain().acks) == 11
