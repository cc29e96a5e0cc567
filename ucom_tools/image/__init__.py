"""Firmware images for the DSP56F803: S-record and Intel HEX files, checked before any use.

:mod:`~ucom_tools.image.model` holds the :class:`Image` every format reads into,
:func:`ucom_tools.image.formats.load_image` reads a file of either format (by its name, or
its content), :mod:`~ucom_tools.image.srec` and :mod:`~ucom_tools.image.ihex` read and
write the records of one format, :mod:`~ucom_tools.image.text` reads the lines of either.
"""
