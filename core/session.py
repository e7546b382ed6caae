"""Zenoh session configuration: from a json5 file, the environment, or the embedded default.

The embedded default is a peer on loopback with multicast scouting off: it listens on
``tcp/127.0.0.1:7447`` and connects to it too, both without failing when the other side is not
there, so the first service started on a machine becomes the rendezvous point of the others.
The command-line flags are those of the zenoh examples: ``--mode``, ``--connect``, ``--listen``,
``--config``, ``--no-multicast-scouting``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final

from protocol.errors import UsageError

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT: Final = "tcp/127.0.0.1:7447"
ENV_CONFIG: Final = "ZENOH_CONFIG"
MODES: Final = ("peer", "client", "router")


@dataclass
class SessionOptions:
    """What the zenoh flags say. ``config_file`` wins over the environment; explicit flags are
    applied on top of whichever base config was chosen."""

    mode: str | None = None
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    config_file: str | None = None
    multicast_scouting: bool | None = None


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the zenoh example flags to a parser."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", "-m", choices=MODES, help="zenoh session mode")
    group.add_argument(
        "--connect",
        "-e",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to connect to (repeatable), e.g. tcp/10.0.0.2:7447",
    )
    group.add_argument(
        "--listen",
        "-l",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on (repeatable)",
    )
    group.add_argument(
        "--config",
        "-c",
        dest="zenoh_config",
        metavar="FILE",
        help=f"zenoh json5 config file (default: ${ENV_CONFIG} or embedded)",
    )
    group.add_argument(
        "--no-multicast-scouting",
        dest="multicast_scouting",
        action="store_false",
        default=None,
        help="disable multicast scouting (already off in the embedded default)",
    )


def options_from_args(args: argparse.Namespace) -> SessionOptions:
    return SessionOptions(
        mode=args.mode,
        connect=list(args.connect or []),
        listen=list(args.listen or []),
        config_file=args.zenoh_config,
        multicast_scouting=args.multicast_scouting,
    )


def _default_json() -> dict[str, Any]:
    return {
        "mode": "peer",
        "connect": {"endpoints": [DEFAULT_ENDPOINT], "exit_on_failure": False},
        "listen": {"endpoints": [DEFAULT_ENDPOINT], "exit_on_failure": False},
        "scouting": {"multicast": {"enabled": False}},
    }


def make_config(options: SessionOptions | None = None, *, env: os._Environ | dict | None = None):
    """Build a ``zenoh.Config``: file (``--config``) > ``$ZENOH_CONFIG`` > embedded default,
    then the explicit flags on top. Raises ``ValueError`` naming the file on a bad config."""
    import zenoh

    options = options or SessionOptions()
    env = os.environ if env is None else env
    if options.config_file:
        try:
            conf = zenoh.Config.from_file(options.config_file)
        except Exception as exc:
            raise UsageError(f"{options.config_file}: invalid zenoh config: {exc}") from None
    elif env.get(ENV_CONFIG):
        try:
            conf = zenoh.Config.from_file(env[ENV_CONFIG])
        except Exception as exc:
            raise UsageError(
                f"${ENV_CONFIG}={env[ENV_CONFIG]}: invalid zenoh config: {exc}"
            ) from None
    else:
        conf = zenoh.Config.from_json5(json.dumps(_default_json()))
    if options.mode:
        if options.mode not in MODES:
            raise UsageError(f"--mode {options.mode!r}: expected one of {MODES}")
        conf.insert_json5("mode", json.dumps(options.mode))
    if options.connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(options.connect)))
    if options.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(options.listen)))
    if options.multicast_scouting is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(options.multicast_scouting))
    return conf


def loopback_config(listen: Sequence[str] = (), connect: Sequence[str] = ()):
    """A peer config on explicit loopback endpoints with scouting off (tests, benchmarks)."""
    import zenoh

    doc = {
        "mode": "peer",
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False}},
    }
    return zenoh.Config.from_json5(json.dumps(doc))


def drain_replies(handler: Any) -> tuple[list[Any], bool]:
    """The replies a Zenoh query's channel holds now, without waiting, and whether the query is
    over (every reply in, or its timeout passed): ``handler`` is what ``get`` returned with the
    default channel. A worker loop polls a long query with this instead of blocking on it."""
    import zenoh

    replies = []
    while True:
        try:
            reply = handler.try_recv()
        except zenoh.ZError:  # empty and closed: the query is over
            return replies, True
        if reply is None:
            return replies, False
        replies.append(reply)
