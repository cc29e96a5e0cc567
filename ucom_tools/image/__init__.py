"""Firmware images for the DSP56F803: S-record and Intel HEX files, checked before any use."""

from ucom_tools.image.formats import load_image
from ucom_tools.image.srec import Image, parse_image

__all__ = ["Image", "load_image", "parse_image"]
