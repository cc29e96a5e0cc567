"""A Foxglove layout for a robot (``ucom remote layout``): the panels that show its
joints, its events and its buses, for the app or Lichtblick to open beside ``remote run
--foxglove`` or a ``--record run.mcap`` (the same topics, ``ucom(1)``, FOXGLOVE).

Built with ``foxglove.layouts`` (foxglove-sdk's own layout classes, which write the JSON
the app imports) from the robot's topology and trees alone, no running robot: one tab
per board with joints, a plot per joint of its joint sensor against its target (what
an engineer tuning a gain watches) and one of its velocity; a tab with the run's events
(``/events``, a Log panel); a last tab with the latest frame of the first bus
(``/CAN0/frames``; the panel's topic field picks another bus).  The frames have a tab of
their own and show one bus at a time: a client subscribes to what the open tab shows, and a
browser sent every frame of ARMAR-III's four buses (25,000 a second) fell behind by
seconds and lost the events beside them (Lichtblick in headless Chromium, two cores).

Lichtblick (``--for lichtblick``, the format of Foxglove Studio 1.x) reads fewer of a
plot's settings than the Foxglove app: its panel titles under ``lichtblickPanelTitle``;
no line styles (the target is drawn wider, in a colour of its own, so that the joint
sensor shows on it); and a plot with ``followingViewWidth`` stays empty when it plays a
recording (Lichtblick 1.28): its plots show the whole time instead.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

from foxglove import layouts as fl

from ucom_tools.edgelists.axes import Role
from ucom_tools.gateway.joints import Joint, RobotJoints
from ucom_tools.trace.mcap_record import topic_chunk, value_key

EVENTS_TOPIC = "/events"


def values_topic(joint: Joint) -> str:
    """The topic of the joint's board's values (as :func:`~ucom_tools.trace.mcap_record.
    layout` names it: prefixes are unique robot-wide, a board without one by its bus
    and seq ID)."""
    b = joint.board
    chunk = topic_chunk(b.prefix) if b.prefix else f"{topic_chunk(b.bus)}/{b.position + 1}"
    return f"/{chunk}/values"


def _path(joint: Joint, role: Role) -> str | None:
    edge = dict(joint.roles).get(role)
    return None if edge is None else f"{values_topic(joint)}.{value_key(edge.unique)}"


def _series(path: str, label: str, *, dashed: bool = False) -> fl.PlotSeries:
    return fl.PlotSeries(value=path, label=label, enabled=True, timestamp_method="receiveTime",
                         line_style="dashed" if dashed else "solid",
                         line_interpolation="step" if dashed else "linear")


def joint_panels(joint: Joint) -> list[fl.BasePanel]:
    """The joint's plots: position against target; velocity (against its target)."""
    panels = [_plot(joint, "position", ((Role.JOINT_SENSOR, "position", False),
                                        (Role.TARGET, "target", True))),
              _plot(joint, "velocity", ((Role.VELOCITY, "velocity", False),
                                        (Role.TARGET_VEL, "velocity target", True)))]
    return [p for p in panels if p is not None]


def _plot(joint: Joint, what: str, series: tuple[tuple[Role, str, bool], ...],
          ) -> fl.PlotPanel | None:
    """A plot of the joint's edges of ``series`` (role, label, dashed) that it has."""
    paths = [_series(path, f"{joint.name} {label}", dashed=dashed)
             for role, label, dashed in series
             if (path := _path(joint, role)) is not None]
    if not paths:
        return None
    return fl.PlotPanel(title=f"{joint.name}: {what}", config=fl.PlotConfig(
        paths=paths, show_legend=True, legend_display="top", time_window_mode="sliding",
        following_view_width=10.0))


def _column(panels: list[fl.BasePanel]) -> Any:
    if len(panels) == 1:
        return panels[0]
    return fl.SplitContainer(direction="column",
                             items=[fl.SplitItem(content=p) for p in panels])


def _row(contents: list[Any]) -> Any:
    if len(contents) == 1:
        return contents[0]
    return fl.SplitContainer(direction="row",
                             items=[fl.SplitItem(content=c) for c in contents])


def _boards(joints: Iterable[Joint]) -> list[tuple[str, list[Joint]]]:
    """The joints by board, in topology order, each board named by its placement."""
    out: dict[tuple[str, int], tuple[str, list[Joint]]] = {}
    for j in joints:
        key = (j.board.bus, j.board.position)
        name = j.board.placement or j.board.prefix or j.board.where
        out.setdefault(key, (name, []))[1].append(j)
    return list(out.values())


def robot_layout(robot: RobotJoints, buses: Iterable[str]) -> fl.Layout:
    """The layout: a tab per board with joints, and the events and frames of ``buses``."""
    tabs = [fl.TabItem(title=name, content=_row([_column(joint_panels(j)) for j in group]))
            for name, group in _boards(robot.joints)]
    tabs.append(fl.TabItem(title="events", content=fl.LogPanel(
        title="events", config=fl.LogConfig(topic_to_render=EVENTS_TOPIC))))
    first = next(iter(buses), None)
    if first is not None:
        tabs.append(fl.TabItem(title="frames", content=fl.RawMessagesPanel(
            title="frames (its topic picks the bus)", config=fl.RawMessagesConfig(
                topic_path=f"/{topic_chunk(first)}/frames"))))
    return fl.Layout(content=fl.TabContainer(tabs=tabs))


FORMATS = ("foxglove", "lichtblick")
"""``foxglove``: foxglove-sdk's layout JSON (the Foxglove app); ``lichtblick``: the
format of Foxglove Studio 1.x that Lichtblick keeps (panels by id in ``configById``, a
binary split tree in ``layout``)."""


STUDIO_TYPES = {"Log": "RosOut"}
"""Panels Studio 1.x (and Lichtblick) names otherwise than the SDK."""
STUDIO_TITLE_KEYS = ("lichtblickPanelTitle", "foxglovePanelTitle")
"""Where a panel's title goes: Lichtblick's key since mid-2025, Studio 1.x's before."""
STUDIO_SERIES = {"solid": {"color": "#1f77b4", "lineSize": 1.5},
                 "dashed": {"color": "#ff7f0e", "lineSize": 4}}
"""A plot's series in Studio 1.x's form, by the SDK's line style (which it does not
read): a target (dashed) wide and orange, beneath the joint's own value."""
STUDIO_DROPPED = ("timeWindowMode", "followingViewWidth")
"""A plot's settings left out (the module docstring: a recording's plots stay empty)."""


def studio_plot(cfg: dict[str, Any]) -> dict[str, Any]:
    """A Plot panel's config of the SDK in Studio 1.x's form."""
    out = {k: v for k, v in cfg.items() if k not in STUDIO_DROPPED}
    paths = []
    for series in cfg.get("paths", []):
        style = series.get("lineStyle", "solid")
        kept = {k: v for k, v in series.items()
                if k not in ("lineStyle", "lineInterpolation")}
        paths.append({**kept, **STUDIO_SERIES.get(style, STUDIO_SERIES["solid"])})
    out["paths"] = paths
    return out


def layout_json(robot: RobotJoints, form: str = "foxglove") -> str:
    """The layout as the JSON the app imports (Layouts, Import from file)."""
    buses = [b.name for b in robot.topology.buses]
    text = robot_layout(robot, buses).to_json()
    if form == "foxglove":
        return text
    return json.dumps(studio_layout(json.loads(text)), indent=2)


def studio_layout(sdk: dict[str, Any]) -> dict[str, Any]:
    """The SDK's layout document in Studio 1.x's form: each panel under an id
    (``Plot!3``) in ``configById`` with its title, tabs as a ``Tab`` panel whose tabs hold
    their own split trees, a split of n items as nested halves (``first``, ``second``,
    ``direction``, ``splitPercentage``)."""
    config: dict[str, Any] = {}
    count = [0]

    def node(content: dict[str, Any]) -> Any:
        kind = content["type"]
        if kind == "panel":
            title = {k: content["title"] for k in STUDIO_TITLE_KEYS} \
                if content.get("title") else {}
            cfg = content.get("config", {})
            if content["panelType"] == "Plot":
                cfg = studio_plot(cfg)
            kind = STUDIO_TYPES.get(content["panelType"], content["panelType"])
            return panel(kind, {**cfg, **title})
        if kind == "tabs":
            return panel("Tab", {"activeTabIdx": content.get("selectedTabIndex", 0),
                                 "tabs": [{"title": t["title"], "layout": node(t["content"])}
                                          for t in content["tabs"]]})
        if kind in ("split", "stack"):
            items = content["items"]
            direction = content.get("direction", "column")
            return halves([(float(i.get("proportion", 1)), node(i["content"]))
                           for i in items], direction)
        raise ValueError(f"a layout node of type {kind!r}")

    def panel(kind: str, cfg: dict[str, Any]) -> str:
        count[0] += 1
        name = f"{kind}!{count[0]}"
        config[name] = cfg
        return name

    def halves(items: list[tuple[float, Any]], direction: str) -> Any:
        if len(items) == 1:
            return items[0][1]
        cut = len(items) // 2
        first, second = items[:cut], items[cut:]
        share = sum(w for w, _ in first) / sum(w for w, _ in items)
        return {"first": halves(first, direction), "second": halves(second, direction),
                "direction": direction, "splitPercentage": round(100 * share, 3)}

    root = node(sdk["content"])
    return {"configById": config, "globalVariables": {}, "userNodes": {},
            "playbackConfig": {"speed": 1}, "layout": root}


__all__ = ["EVENTS_TOPIC", "FORMATS", "joint_panels", "layout_json", "robot_layout",
           "studio_layout", "studio_plot", "values_topic"]
