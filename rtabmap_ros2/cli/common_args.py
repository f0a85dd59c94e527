"""Arguments shared by several subcommands: ``--config`` and ``--set``."""

from __future__ import annotations

import argparse
import logging

from rtabmap_ros2.core.params import Params, default_config_path

log = logging.getLogger(__name__)


def add_param_arguments(parser: argparse.ArgumentParser, default_config: str | None = None,
                        base: str | None = None) -> None:
    """Add ``--config FILE`` and repeatable ``--set NAME=VALUE``.

    Args:
        parser: the subcommand's parser.
        default_config: shipped config file loaded when ``--config`` is not given.
        base: what ``--config`` and ``--set`` apply over instead, when there is one (export: the
            parameters stored with the database; the default config then only without them).
    """
    if base:
        config_help = (f"parameter YAML (plain nested keys or a ROS 2 parameter file) applied over {base}; "
                       f"without them, the shipped config/{default_config}")
    else:
        config_help = ("parameter YAML (plain nested keys or a ROS 2 parameter file)"
                       + (f" applied over the shipped config/{default_config}, as the node's --params-file"
                          if default_config else " applied over the defaults"))
    parser.add_argument("--config", metavar="FILE", default=None, help=config_help)
    parser.add_argument(
        "--set", metavar="NAME=VALUE", action="append", default=[], dest="overrides",
        help="override one parameter, e.g. --set Mem/STMSize=30 or --set memory.stm_size=30 (repeatable)",
    )
    parser.set_defaults(default_config=default_config)


def _default_config(args: argparse.Namespace) -> str | None:
    if not args.default_config:
        return None
    path = default_config_path(args.default_config)
    return str(path) if path else None


def params_from_args(args: argparse.Namespace) -> Params:
    """Parameters: the defaults, the command's shipped config over them (``map``: config/rtabmap.yaml),
    ``--config`` over that, then ``--set``. A user's file names what it changes, as a parameter file
    given to the node (whose base is the same shipped config): replacing the shipped config
    instead, an rtabmap_ros file of a few settings silently dropped every SLAM setting it ships."""
    params = Params()
    for config in (_default_config(args), args.config):
        if config:
            params = Params.from_yaml(config, base=params)
    return params.with_overrides(args.overrides)


def params_for_database(args: argparse.Namespace, database) -> tuple[Params, str]:
    """Parameters for a command reading a map database (``export``): the ones stored with it (what
    ``map`` or the node mapped with), then ``--config`` and ``--set`` over them; the shipped config
    when the database holds none, or holds some this version cannot read (a warning says so).

    Returns:
        ``(params, origin)``: origin is a sentence saying where they came from, for the user.

    Raises:
        DatabaseError: the database is missing or not a map database.
        ParameterError: a bad ``--config`` or ``--set``.
    """
    from rtabmap_ros2.core.database import Database
    from rtabmap_ros2.errors import ParameterError

    with Database(database, read_only=True) as db:
        stored = db.get_parameters()
    params, origin = None, ""
    if stored:
        try:
            params, origin = Params.from_stored(stored), "those stored with the database (the ones it was mapped with)"
        except ParameterError as exc:
            log.warning("the parameters stored with %s cannot be read by this version (%s): using the shipped "
                        "config instead", database, exc)
    if params is None:
        config = _default_config(args)
        params = Params.from_yaml(config) if config else Params()
        origin = (f"the shipped {args.default_config}" if config else "the defaults") + " (the database holds none)"
    if args.config:
        params = Params.from_yaml(args.config, base=params)
        origin += f", then --config {args.config}"
    if args.overrides:
        params = params.with_overrides(args.overrides)
        origin += ", then --set " + " ".join(args.overrides)
    return params, origin
