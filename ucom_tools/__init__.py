"""ucom-tools: toolchain, bus console and virtual fleet for UCoM controller boards."""

from ucom_tools import compiled as _compiled

__version__ = "0.1.0"

_compiled.activate()  # before any of the compiled modules can be imported
