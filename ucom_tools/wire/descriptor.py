"""The image descriptor: what a DSP program was built for, at a fixed place in P: flash.

32 words at P:7DE0-7DFF (the end of program flash), each word low byte first like all
image words:

  word 0-1   magic "UCOM" (0x4355, 0x4D4F)
  word 2     descriptor format (1)
  word 3     DSP-Board-ID (0-15)
  word 4     App-ID (0-127)
  word 5     FPGA major version the program was built for (0-63)
  word 6     FPGA minor version (0-63)
  word 7     program version: major << 8 | minor
  word 8-23  program name, 32 Latin-1 characters, NUL padded, two per word
  word 24-30 reserved, 0xFFFF
  word 31    check word: the 16-bit sum of all 32 words is 0
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from ucom_tools.errors import FrameError
from ucom_tools.wire.codes import Space

DESCRIPTOR_ADDRESS = 0x7DE0
DESCRIPTOR_WORDS = 32
MAGIC = (0x4355, 0x4D4F)
FORMAT = 1
NAME_CHARS = 32


@dataclass(frozen=True, slots=True)
class ImageDescriptor:
    board_id: int
    app_id: int
    fpga_major: int
    fpga_minor: int
    version: tuple[int, int]
    name: str

    def __post_init__(self) -> None:
        for field, value, bits in (("Board-ID", self.board_id, 4), ("App-ID", self.app_id, 7),
                                   ("FPGA major", self.fpga_major, 6),
                                   ("FPGA minor", self.fpga_minor, 6),
                                   ("version major", self.version[0], 8),
                                   ("version minor", self.version[1], 8)):
            if not 0 <= value < (1 << bits):
                raise FrameError(field, f"must fit {bits} bits, got {value}")

    def to_words(self) -> list[int]:
        raw = self.name.encode("latin-1", "replace")[:NAME_CHARS].ljust(NAME_CHARS, b"\0")
        words = [*MAGIC, FORMAT, self.board_id, self.app_id, self.fpga_major, self.fpga_minor,
                 (self.version[0] << 8) | self.version[1]]
        words += [raw[i] | (raw[i + 1] << 8) for i in range(0, NAME_CHARS, 2)]
        words += [0xFFFF] * 7
        words.append((-sum(words)) & 0xFFFF)
        return words

    @classmethod
    def from_words(cls, words: Sequence[int]) -> ImageDescriptor | None:
        """The descriptor in these 32 words; None if there is none (no magic)."""
        if len(words) != DESCRIPTOR_WORDS or tuple(words[:2]) != MAGIC:
            return None
        if sum(words) & 0xFFFF:
            raise FrameError("image descriptor", "check word does not match (corrupt)")
        if words[2] != FORMAT:
            raise FrameError("image descriptor", f"unknown format {words[2]}")
        raw = bytes(b for w in words[8:24] for b in (w & 0xFF, w >> 8))
        return cls(words[3], words[4], words[5], words[6], (words[7] >> 8, words[7] & 0xFF),
                   raw.rstrip(b"\0").decode("latin-1"))

    @classmethod
    def from_image(cls, words: Mapping[tuple[Space, int], int]) -> ImageDescriptor | None:
        block = [words.get((Space.P, DESCRIPTOR_ADDRESS + i)) for i in range(DESCRIPTOR_WORDS)]
        if any(w is None for w in block):
            return None
        return cls.from_words([w for w in block if w is not None])

    def placement(self) -> dict[tuple[Space, int], int]:
        return {(Space.P, DESCRIPTOR_ADDRESS + i): w for i, w in enumerate(self.to_words())}
