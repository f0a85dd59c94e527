"""Declare the node's ROS parameters from the typed dataclasses and read them back into Params.

One ROS parameter per field of :class:`~rtabmap_ros2.core.params.Params`, under its public name
(``memory.stm_size``; plain names such as ``database_path`` for the node's own fields), with a
``ParameterDescriptor`` whose description is the field's doc and unit. Defaults come from the
shipped ``config/rtabmap.yaml`` when it is found (``default_config_path()``), else from the
dataclasses; ``--ros-args -p NAME:=VALUE`` and ``--params-file`` override them as usual.

The synchroniser's rate, mode and queue are declared under the names rtabmap_ros users know,
``detection_rate``, ``approx_sync`` and ``sync_queue_size`` (issue 5), instead of their dotted
names ``sync.rate_hz``, ``sync.approx_sync``, ``sync.queue_size``: one name per setting.

RTAB-Map's own names are accepted as ROS parameters too, as rtabmap_ros users pass them
(``-p Mem/STMSize:=10``, also as strings: ``-p Mem/STMSize:="'10'"``): every override named
``Group/Name`` that :data:`~rtabmap_ros2.core.params.RTABMAP_ALIASES` knows is declared under that
name and applied after the plain ones (it wins); an unknown ``Group/Name`` gets one warning naming
the closest known name, and is ignored.

Parameters are read once at start (``read_only``): the core is built from them.
"""

from __future__ import annotations

import difflib
import re
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor

from rtabmap_ros2.core.params import RTABMAP_ALIASES, Params, default_config_path

# RTAB-Map's parameter names: Group/Name (rclpy's qos_overrides./topic... parameters are not).
RTABMAP_NAME = re.compile(r"[A-Za-z][A-Za-z0-9]*/[A-Za-z][A-Za-z0-9_]*")

# ROS name -> dotted field, for the settings declared under rtabmap_ros's names.
NODE_SYNC_NAMES = {
    "detection_rate": "sync.rate_hz",
    "approx_sync": "sync.approx_sync",
    "sync_queue_size": "sync.queue_size",
}
_DOTTED_TO_ROS = {dotted: ros for ros, dotted in NODE_SYNC_NAMES.items()}


def defaults(config_path: str | Path | None = None) -> Params:
    """The parameters before ROS overrides: ``config_path``, else the shipped config, else the papers'."""
    path = Path(config_path) if config_path is not None else default_config_path()
    return Params.from_yaml(path) if path is not None else Params()


def parameter_table(params: Params) -> list[tuple[str, str, Any, str]]:
    """``(ROS name, public name, value, description)`` for every declared parameter."""
    table = []
    for public, value, doc, unit in params.public_items():
        ros_name = _DOTTED_TO_ROS.get(public, public)
        description = f"{doc} [{unit}]" if unit else doc
        table.append((ros_name, public, value, description))
    return table


def declare_parameters(node, base: Params | None = None) -> Params:
    """Declare every parameter on ``node`` (an ``rclpy.node.Node``) and return the values in force.

    Args:
        node: the node; its overrides (``-p``, ``--params-file``) take precedence over ``base``.
        base: defaults (``defaults()`` when None: the shipped config file or the papers' values).

    Raises:
        ParameterError: an override has a value the dataclasses reject (names the parameter).
    """
    params = defaults() if base is None else base
    for ros_name, _public, value, description in parameter_table(params):
        # dynamic_typing: accept 1 for a float (or 1.0 for an int) and let Params coerce and
        # validate it with a clear ParameterError, instead of rclpy's type exception.
        node.declare_parameter(ros_name, value, ParameterDescriptor(
            description=description, read_only=True, dynamic_typing=True))
    return apply_rtabmap_names(node, read_parameters(node, params))


def rtabmap_name_overrides(node) -> dict[str, Any]:
    """The overrides given to ``node`` under RTAB-Map-style ``Group/Name`` names (``-p``, params file).

    rclpy keeps every override, declared or not, in ``Node._parameter_overrides`` (no public accessor
    lists undeclared ones).
    """
    return {name: parameter.value for name, parameter in node._parameter_overrides.items()
            if RTABMAP_NAME.fullmatch(name)}


def closest_rtabmap_name(name: str) -> str | None:
    """The known RTAB-Map name closest to ``name`` (None when nothing is close)."""
    known = [n for n in RTABMAP_ALIASES if "/" in n]
    match = difflib.get_close_matches(name, known, n=1, cutoff=0.5)
    if not match:   # same group, e.g. Mem/Foo -> a Mem/ name
        match = [n for n in known if n.split("/")[0].lower() == name.split("/")[0].lower()][:1]
    return match[0] if match else None


def apply_rtabmap_names(node, params: Params) -> Params:
    """Declare and apply the overrides named like RTAB-Map's (``Mem/STMSize``); warn about unknown ones."""
    for name, value in sorted(rtabmap_name_overrides(node).items()):
        if name not in RTABMAP_ALIASES:
            closest = closest_rtabmap_name(name)
            hint = f"; did you mean {closest}?" if closest else ""
            node.get_logger().warning(
                f"unknown RTAB-Map parameter {name}:={value!r} ignored{hint} "
                f"(rtabmap-ros2 params lists every parameter with its RTAB-Map name)")
            continue
        dotted = RTABMAP_ALIASES[name][0]
        node.declare_parameter(name, value, ParameterDescriptor(
            description=f"RTAB-Map name of {dotted}", read_only=True, dynamic_typing=True))
        params = params.with_value(name, value)
        node.get_logger().info(f"{name}:={value!r} -> {dotted}")
    return params

def read_parameters(node, base: Params) -> Params:
    """The declared parameters' current values as Params (validated by the dataclasses)."""
    params = base
    for ros_name, _public, _value, _description in parameter_table(base):
        value = node.get_parameter(ros_name).value
        if value is None:  # declared without a value: keep the default
            continue
        params = params.with_value(ros_name, value)
    return params
