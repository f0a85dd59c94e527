"""Declare the node's ROS parameters from the typed dataclasses and read them back into Params.

One ROS parameter per field of :class:`~rtabmap_ros2.core.params.Params`, under its public name
(``memory.stm_size``; plain names such as ``database_path`` for the node's own fields), with a
``ParameterDescriptor`` whose description is the field's doc and unit. Defaults come from the
shipped ``config/rtabmap.yaml`` when it is found (``default_config_path()``), else from the
dataclasses; ``--ros-args -p NAME:=VALUE`` and ``--params-file`` override them as usual.

The synchroniser's rate, mode and queue are declared under the names rtabmap_ros users know,
``detection_rate``, ``approx_sync`` and ``sync_queue_size`` (issue 5), instead of their dotted
names ``sync.rate_hz``, ``sync.approx_sync``, ``sync.queue_size``: one name per setting.

Parameters are read once at start (``read_only``): the core is built from them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor

from rtabmap_ros2.core.params import Params, default_config_path

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
    return read_parameters(node, params)


def read_parameters(node, base: Params) -> Params:
    """The declared parameters' current values as Params (validated by the dataclasses)."""
    params = base
    for ros_name, _public, _value, _description in parameter_table(base):
        value = node.get_parameter(ros_name).value
        if value is None:  # declared without a value: keep the default
            continue
        params = params.with_value(ros_name, value)
    return params
