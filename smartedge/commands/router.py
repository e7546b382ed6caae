"""``smartedge router``: the site's Zenoh router, from the smartedge package itself.

A Zenoh session in router mode with the site's router config (``deploy/zenoh/router.json5`` or
``router-tls.json5``, installed as ``/etc/smartedge/zenoh-router.json5``), so that a site needs
no zenohd: the edge boards, the robot bridges, the backend and the viewer connect to it as
clients. It logs its zid and listen endpoints, optionally the number of connected sessions every
``--status-period`` seconds, speaks sd_notify (READY, WATCHDOG, STOPPING) like the services, and
runs until SIGTERM/SIGINT, then closes and exits 0.

Exit statuses: 0 after a clean stop; :data:`~core.runtime.EXIT_CONFIG` (78) when the config
file is missing or not a valid zenoh config (restarting cannot fix it); 1 when zenoh cannot open
the router with a valid config (an endpoint taken, a TLS certificate unreadable): the message
names the file, and systemd retries, since an address that is not up yet or a port still held
by a stopping router passes on its own; 2 on a usage error.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import signal
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any, Final

import zenoh

from core.runtime import EXIT_CONFIG, sd_notify, watchdog_period_s
from core.session import SessionOptions, make_config
from protocol.errors import SmartedgeError, UsageError

log = logging.getLogger(__name__)

#: where install-backend.sh puts the site's router config
DEFAULT_CONFIG_HINT: Final = "/etc/smartedge/zenoh-router.json5"


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``smartedge router``."""
    parser = argparse.ArgumentParser(
        prog="smartedge router",
        description="Run the site's Zenoh router (a zenoh session in router mode); zenohd is "
        "then optional. Clients connect to the listen endpoints of the config.",
    )
    parser.add_argument(
        "--config",
        "-c",
        dest="zenoh_config",
        required=True,
        metavar="FILE",
        help=f"zenoh json5 router config, plain or TLS (installed as {DEFAULT_CONFIG_HINT}); "
        "its mode is forced to router",
    )
    parser.add_argument(
        "--listen",
        "-l",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on instead of the config's (repeatable), e.g. "
        "tcp/0.0.0.0:7447",
    )
    parser.add_argument(
        "--connect",
        "-e",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="another router to connect to instead of the config's (repeatable)",
    )
    parser.add_argument(
        "--status-period",
        type=float,
        default=0.0,
        metavar="S",
        help="log the number of connected routers, peers and clients every S seconds "
        "(default 0: only when it changes)",
    )
    return parser


def router_config(
    config_file: str, listen: Sequence[str] = (), connect: Sequence[str] = ()
) -> zenoh.Config:
    """The ``zenoh.Config`` of the router: ``config_file`` with mode router and the explicit
    endpoints on top. Raises :class:`~protocol.errors.UsageError` naming the file (one line)."""
    options = SessionOptions(
        mode="router", listen=list(listen), connect=list(connect), config_file=config_file
    )
    try:
        return make_config(options)
    except UsageError as exc:
        raise UsageError(one_line(str(exc))) from None


def one_line(text: str) -> str:
    """A zenoh error message on one line: without the Rust source locations and the json5
    parser's ascii art (``--> 3:7``, the echoed source line, ``^---``)."""
    text = re.sub(r"\s+at \S+\.rs:\d+\.?", "", text)
    text = re.sub(r"-->\s*(\d+):(\d+)", r"line \1, column \2:", text)
    parts = []
    for raw in text.splitlines():
        line = raw.strip()
        # the echoed source line and its markers go; "= expected ..." is the reason
        if not (re.fullmatch(r"\d*\s*\|.*", line) or re.fullmatch(r"[\^\-~ ]*", line)):
            parts.append(line.removeprefix("= "))
    return " ".join(" ".join(parts).split())


def connected(session: Any) -> dict[str, int]:
    """Sessions connected to ``session`` by kind: ``{"routers": n, "peers": n, "clients": n}``.

    ``SessionInfo.transports`` (recent eclipse-zenoh 1.x) lists clients too; without it only
    routers and peers are counted."""
    info = session.info
    transports = getattr(info, "transports", None)
    if transports is not None:
        counts = {"routers": 0, "peers": 0, "clients": 0}
        for transport in transports():
            kind = str(transport.whatami).lower()
            counts[f"{kind}s"] = counts.get(f"{kind}s", 0) + 1
        return counts
    return {"routers": len(list(info.routers_zid())), "peers": len(list(info.peers_zid()))}


def _format_counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{n} {kind}" for kind, n in counts.items())


def run_router(config: Any, stop: threading.Event, *, status_period_s: float = 0.0) -> None:
    """Open the router session on ``config`` (a ``zenoh.Config``) and hold it until ``stop`` is
    set. Logs the zid and listen endpoints, and the connected sessions whenever they change or
    every ``status_period_s`` (> 0); pings the systemd watchdog. Raises ``zenoh.ZError`` when
    the session cannot be opened."""
    endpoints = json.loads(config.get_json("listen/endpoints") or "[]")
    with zenoh.open(config) as session:
        log.info("zenoh router %s listening on %s", session.info.zid(),
                 ", ".join(endpoints) or "(no endpoints)")
        sd_notify("READY=1")
        watchdog = watchdog_period_s()
        now = time.monotonic()
        next_status = now + status_period_s if status_period_s > 0 else float("inf")
        next_watchdog = now
        last: dict[str, int] | None = None
        try:
            while not stop.is_set():
                now = time.monotonic()
                counts = connected(session)
                if counts != last or now >= next_status:
                    log.info("connected: %s", _format_counts(counts))
                    last = counts
                    if status_period_s > 0:
                        next_status = now + status_period_s
                if watchdog is not None and now >= next_watchdog:
                    sd_notify("WATCHDOG=1")
                    next_watchdog = now + watchdog
                stop.wait(0.5)
        finally:
            sd_notify("STOPPING=1")
            log.info("zenoh router %s stopping", session.info.zid())


def main(argv: Sequence[str]) -> int:
    """``smartedge router``: run until SIGTERM/SIGINT; see the module docstring for the exit
    statuses."""
    args = build_parser().parse_args(list(argv))
    if args.status_period < 0:
        print("smartedge router: --status-period must be >= 0", file=sys.stderr)
        return 2
    try:
        config = router_config(args.zenoh_config, args.listen, args.connect)
    except SmartedgeError as exc:
        print(f"smartedge router: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    # zenoh's own log (stderr, so journald): RUST_LOG selects it; the access control logs each
    # message it denies at trace level (RUST_LOG=trace, verbose); without RUST_LOG, errors only
    zenoh.init_log_from_env_or("error")
    stop = threading.Event()

    def on_signal(*_: object) -> None:
        # the handler runs in the main thread, which may be inside stop.wait() holding the
        # event's lock: setting it here could wait for that lock forever; a thread waits instead
        threading.Thread(target=stop.set, daemon=True).start()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    try:
        run_router(config, stop, status_period_s=args.status_period)
    except zenoh.ZError as exc:
        print(f"smartedge router: cannot open the router with {args.zenoh_config}: "
              f"{one_line(str(exc))}", file=sys.stderr)
        return 1
    return 0
