"""Arguments shared by several subcommands: ``--config`` and ``--set``."""

from __future__ import annotations

import argparse

from rtabmap_ros2.core.params import Params, default_config_path


def add_param_arguments(parser: argparse.ArgumentParser, default_config: str | None = None) -> None:
    """Add ``--config FILE`` and repeatable ``--set NAME=VALUE``."""
    parser.add_argument(
        "--config", metavar="FILE", default=None,
        help="parameter YAML (plain nested keys or a ROS 2 parameter file)"
        + (f"; default: the shipped config/{default_config}" if default_config else "; default: paper defaults"),
    )
    parser.add_argument(
        "--set", metavar="NAME=VALUE", action="append", default=[], dest="overrides",
        help="override one parameter, e.g. --set Mem/STMSize=30 or --set memory.stm_size=30 (repeatable)",
    )
    parser.set_defaults(default_config=default_config)


def params_from_args(args: argparse.Namespace) -> Params:
    """Parameters: defaults, then the config file, then ``--set`` overrides."""
    params = Params()
    config = args.config
    if config is None and args.default_config:
        path = default_config_path(args.default_config)
        config = str(path) if path else None
    if config:
        params = Params.from_yaml(config)
    return params.with_overrides(args.overrides)
