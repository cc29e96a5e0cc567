"""FPGA version registers (Tab. B.5/B.6), the image descriptor, and the virtual FPGA."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.conftest import chain_topology
from ucom_tools.errors import FrameError
from ucom_tools.memory import is_fpga_address
from ucom_tools.virtual.hardware.fpga import ExternalMemory, QuadratureDecoder, VirtualFpga
from ucom_tools.wire.codes import Space
from ucom_tools.wire.descriptor import DESCRIPTOR_ADDRESS, ImageDescriptor
from ucom_tools.wire.fpga import FpgaVersion, Reg
from ucom_tools.wire.ids import seq

versions = st.builds(FpgaVersion, st.integers(0, 15), st.integers(0, 127), st.integers(0, 63),
                     st.integers(0, 63), st.integers(0, 3), st.integers(0, 3))


@given(versions)
def test_version_registers_round_trip(v: FpgaVersion) -> None:
    r1, r2 = v.register1(), v.register2()
    assert 0 <= r1 <= 0xFFFF and 0 <= r2 <= 0xFFFF
    assert not r1 & 0x10 and not r2 & 0x0F  # bit 4 of reg 1 is 0, bits 3-0 of reg 2 unused
    assert FpgaVersion.decode(r1, r2) == v


def test_version_register_bit_layout() -> None:
    v = FpgaVersion(board_id=0b1010, app_id=0b1100101, major=0b100001, minor=0b010010,
                    ikl=0b11, ikh=0b01)
    assert v.register1() == 0b11_1100101_01_0_1010
    assert v.register2() == 0b100001_010010_0000
    assert FpgaVersion.decode(v.register1(), v.register2() | 0x7) == v  # unused bits ignored


def test_version_fields_are_range_checked() -> None:
    with pytest.raises(FrameError, match="App-ID"):
        FpgaVersion(1, 128, 1, 0)
    with pytest.raises(FrameError, match="Board-ID"):
        FpgaVersion(16, 1, 1, 0)
    with pytest.raises(FrameError, match="bit 4"):
        FpgaVersion.decode(0x0010, 0)


@given(st.builds(ImageDescriptor, st.integers(0, 15), st.integers(0, 127), st.integers(0, 63),
                 st.integers(0, 63), st.tuples(st.integers(0, 255), st.integers(0, 255)),
                 st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126),
                         max_size=32)))
def test_descriptor_round_trips(d: ImageDescriptor) -> None:
    words = d.to_words()
    assert len(words) == 32 and sum(words) & 0xFFFF == 0
    assert ImageDescriptor.from_words(words) == d
    assert ImageDescriptor.from_image(d.placement()) == d
    assert min(d.placement()) == (Space.P, DESCRIPTOR_ADDRESS)


def test_descriptor_absent_or_corrupt() -> None:
    assert ImageDescriptor.from_words([0xFFFF] * 32) is None
    words = ImageDescriptor(1, 1, 1, 0, (1, 0), "x").to_words()
    words[4] ^= 1
    with pytest.raises(FrameError, match="check word"):
        ImageDescriptor.from_words(words)


def test_address_decoding_follows_b1() -> None:
    assert [is_fpga_address(a) for a in (0x3FFF, 0x4000, 0x403F, 0x4040, 0xC000)] == [
        False, True, True, False, False]
    mem = ExternalMemory(VirtualFpga(FpgaVersion(1, 1, 1, 0), 1))
    mem.write(0x4020, 0x1234)  # FPGA register
    mem.write(0x2000, 0xBEEF)  # external RAM
    mem.write(0x4040, 0xCAFE)  # RAM right after the FPGA window
    assert (mem.read(0x4020), mem.read(0x2000), mem.read(0x4040)) == (0x1234, 0xBEEF, 0xCAFE)
    assert mem.fpga.registers[0x20] == 0x1234 and 0x4020 not in mem.ram


def test_version_and_board_registers_are_read_only() -> None:
    fpga = VirtualFpga(FpgaVersion(1, 5, 2, 3), plug_board_id=1)
    for reg in (Reg.VERSION1, Reg.VERSION2, Reg.BOARD_ID, Reg.STATUS):
        before = fpga.read(reg)
        fpga.write(reg, 0xFFFF)
        assert fpga.read(reg) == before
    assert FpgaVersion.decode(fpga.read(Reg.VERSION1), fpga.read(Reg.VERSION2)) == \
        FpgaVersion(1, 5, 2, 3)


def test_quadrature_decoders_count_with_prescaler_and_wrap() -> None:
    q = QuadratureDecoder()
    q.feed(5)
    q.feed(-7)
    assert q.count == 0xFFFE  # -2 in 16 bit
    q.set(0x7FFF)
    q.feed(2)
    assert q.count == 0x8001
    q.set(0)
    q.prescale = 4
    for _ in range(10):
        q.feed(1)
    assert q.count == 2  # 10 edges, every 4th counted
    fpga = VirtualFpga(FpgaVersion(1, 1, 1, 0), 1)
    fpga.write(Reg.QUAD_PRESCALE0 + 2, 2)
    fpga.encoder_edges(2, 9)
    assert fpga.read(Reg.QUAD_COUNT0 + 2) == 4
    fpga.write(Reg.QUAD_COUNT0 + 2, 1000)  # settable, e.g. at init
    assert fpga.read(Reg.QUAD_COUNT0 + 2) == 1000


def test_neutral_state_ignores_inputs_disables_outputs_keeps_dsp_access() -> None:
    fpga = VirtualFpga(FpgaVersion(1, 1, 1, 0), plug_board_id=3)  # 3M FPGA, valve board
    assert fpga.neutral and fpga.read(Reg.STATUS) == 1 and fpga.read(Reg.BOARD_ID) == 3
    fpga.write(Reg.OUTPUT_ENABLE, 0b111)
    fpga.inputs = 0x00FF
    fpga.encoder_edges(0, 100)
    assert fpga.outputs_enabled() == 0
    assert fpga.read(Reg.DIGITAL_IN) == 0
    assert fpga.read(Reg.QUAD_COUNT0) == 0
    fpga.write(Reg.QUAD_COUNT0, 42)  # DSP <-> FPGA still works
    assert fpga.read(Reg.QUAD_COUNT0) == 42 and fpga.read(Reg.OUTPUT_ENABLE) == 0b111
    ok = VirtualFpga(FpgaVersion(1, 1, 1, 0), plug_board_id=1)
    ok.write(Reg.OUTPUT_ENABLE, 0b101)
    ok.inputs = 0x0F
    assert (ok.outputs_enabled(), ok.read(Reg.DIGITAL_IN)) == (0b101, 0x0F)


def test_fpga_registers_over_can(host) -> None:
    h = host(chain_topology(2, extra={1: 'fpga = { app_id = 9, major = 3, minor = 2 }'}))
    h.client.init_chain()
    v1, v2, board_id, status = h.client.read_memory(seq(2), Space.X, 0x4000, 4)
    assert FpgaVersion.decode(v1, v2) == FpgaVersion(1, 9, 3, 2)
    assert (board_id, status) == (1, 0)
    info = h.client.info(seq(2))
    assert info.fpga == FpgaVersion(1, 9, 3, 2)
    assert (info.measured_board_id, info.fpga_neutral, info.descriptor) == (1, False, None)
    h.boards[1].fpga.encoder_edges(4, 77)
    assert h.client.read_memory(seq(2), Space.X, 0x4000 + Reg.QUAD_COUNT0 + 4, 1) == [77]
