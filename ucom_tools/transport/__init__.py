"""Transports: python-can buses of our own where python-can's interfaces are not good
enough for a robot tool (every wait must have a deadline)."""

from ucom_tools.transport.socketcand import SocketcandBus

__all__ = ["SocketcandBus"]
