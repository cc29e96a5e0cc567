"""``ucom srec info`` and ``ucom srec progid`` (option 19, Calc ProgID): the old names of
``ucom image info`` and ``ucom image progid``, which read either format."""

from __future__ import annotations

import click

from ucom_tools.cli import image


@click.group("srec")
def srec() -> None:
    """Firmware images (S-record or Intel HEX): the same as 'ucom image info/progid'."""


srec.add_command(image.info)
srec.add_command(image.progid)
