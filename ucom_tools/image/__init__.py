"""Firmware images: Motorola S-record files for the DSP56F803, checked before any use."""

from ucom_tools.image.srec import Image, load_image, parse_image

__all__ = ["Image", "load_image", "parse_image"]
