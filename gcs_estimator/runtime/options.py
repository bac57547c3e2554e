"""Command-line options that more than one command takes, defined once: the run's
commands (cli.py) and the fleet's (`batch`, `trend`: fleet.py) add them from here, each
with its own words where the option means something else there."""

from __future__ import annotations

import argparse

from gcs_estimator.outputs.tables import HISTORY_FORMATS

Parser = argparse._ActionsContainer
"""A parser or one of its argument groups (what add_argument is called on)."""


def group(p: argparse.ArgumentParser, title: str) -> Parser:
    """The parser's argument group of this title (made the first time it is asked for),
    so that options added in different places are listed together in --help."""
    for g in p._action_groups:
        if g.title == title:
            return g
    return p.add_argument_group(title)


def config_option(p: Parser, default: str | None, without: str) -> None:
    """--config: the airframe file; `without`: what happens when it is not given."""
    p.add_argument(
        "--config",
        default=default,
        metavar="FILE",
        help="the airframe file: a TOML path or a shipped name (noc_uav, hfb320); "
        + (f"default: {default}" if default else without),
    )


def set_option(p: Parser) -> None:
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set filter.iterations=3 (repeatable; "
        "`gcs-estimator keys` lists them)",
    )


def out_options(p: Parser, folder: str, force: str) -> None:
    """--out (the folder: `folder` says which and its default) and --force."""
    p.add_argument("--out", default=None, metavar="FOLDER", help=folder)
    p.add_argument("--force", action="store_true", help=force)


def history_option(p: Parser, whose: str) -> None:
    p.add_argument(
        "--history",
        choices=HISTORY_FORMATS,
        default=HISTORY_FORMATS[0],
        help=f"{whose} per-frame history file: parquet (default, compact) or csv",
    )


def vehicle_map_option(p: Parser) -> None:
    p.add_argument(
        "--vehicle-map",
        default=None,
        metavar="TOML",
        help='names of vehicles: a [vehicles] table of "PATTERN or IDENTITY" = "NAME" '
        '(a log path pattern such as "logs/plane_a/*.tlog", or "uid:0123..." or "sys3")',
    )


def trend_view_option(p: Parser) -> None:
    p.add_argument(
        "--view",
        choices=("save", "off"),
        default="save",
        help="the trend's Rerun recording (trend.rrd beside the report): save (default) or off",
    )
