"""``rtabmap-ros2 params``: every parameter with its value, unit and documentation."""

from __future__ import annotations

import argparse

from rtabmap_ros2.cli.common_args import add_param_arguments, params_from_args


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "params", help="list every parameter (dotted name, value, unit, doc) and RTAB-Map aliases",
        description="Print the parameters after --config/--set, as a table or as YAML.")
    add_param_arguments(parser)
    parser.add_argument("--yaml", action="store_true", help="print the values as a YAML config instead")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rtabmap_ros2.core.params import RTABMAP_ALIASES

    params = params_from_args(args)
    if args.yaml:
        import yaml

        print(yaml.safe_dump(params.to_dict(), sort_keys=False), end="")
        return 0
    aliases: dict[str, list[str]] = {}
    for alias, (dotted, _) in RTABMAP_ALIASES.items():
        aliases.setdefault(dotted, []).append(alias)
    for name, value, doc, unit in params.public_items():
        dotted = name if "." in name else f"node.{name}"
        extra = f" (also {', '.join(aliases[dotted])})" if dotted in aliases else ""
        unit_text = f" [{unit}]" if unit else ""
        print(f"{name} = {value!r}{unit_text}{extra}\n    {doc}")
    return 0
