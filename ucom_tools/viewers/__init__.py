"""Viewers of a running robot that others wrote: the run time served where roboticists
look at their robots.

:mod:`.foxglove` serves the Foxglove WebSocket protocol (``remote run --foxglove``,
``browse --foxglove``) with foxglove-sdk's server, for the Foxglove app and Lichtblick;
:mod:`.foxglove_msgs` builds what it sends (topics, JSON schemas, messages) and imports
nothing of the SDK.  Like :mod:`ucom_tools.net`, this is a consumer of a run: it reads the
snapshots and frames the loop hands over, in the consumers' process, never the loop.
"""
