"""ucom-tools: toolchain, bus console and virtual fleet for UCoM controller boards."""

__version__ = "0.1.0"
