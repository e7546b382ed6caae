"""Named plug-ins chosen by a command-line option (``--source``, ``--adapter``).

A service offers a :class:`PluginRegistry`; the top floor registers what it assembles (the
simulation's frame source and robot adapter) before the service builds its parser. A plug-in
has ``add_arguments(parser)`` (its own argument group) and ``build(args, site)``.
"""

from __future__ import annotations

import argparse
import logging
import threading
from typing import Any, Generic, TypeVar

from protocol.errors import UnknownIdError, UsageError

log = logging.getLogger(__name__)

P = TypeVar("P")


class PluginRegistry(Generic[P]):
    """Plug-ins by name for one option (``option`` e.g. ``--source``, ``what`` e.g. ``frame
    source`` in messages). Thread-safe; registering the same plug-in twice is harmless."""

    def __init__(self, option: str, what: str) -> None:
        self.option = option
        self.what = what
        self._lock = threading.Lock()
        self._plugins: dict[str, P] = {}

    def register(self, name: str, plugin: P) -> None:
        """Offer ``plugin`` as ``<option> name``. The same plug-in again is a no-op; another
        plug-in under a taken name is a :class:`UsageError`."""
        if not name or not name.replace("-", "").replace("_", "").isalnum():
            raise UsageError(f"bad {self.what} name {name!r}")
        with self._lock:
            existing = self._plugins.get(name)
            if existing is plugin:
                return
            if existing is not None:
                raise UsageError(f"{self.what} {name!r} is already registered ({existing!r})")
            self._plugins[name] = plugin
        log.debug("%s %r registered", self.what, name)

    def names(self) -> tuple[str, ...]:
        """The registered names, sorted."""
        with self._lock:
            return tuple(sorted(self._plugins))

    def get(self, name: str) -> P:
        """The plug-in registered as ``name`` (:class:`UnknownIdError` naming the known ones)."""
        with self._lock:
            try:
                return self._plugins[name]
            except KeyError:
                raise UnknownIdError(
                    f"unknown {self.what} {name!r}; registered: {', '.join(sorted(self._plugins))}"
                ) from None

    def add_arguments(self, parser: argparse.ArgumentParser, default: str) -> None:
        """The option with the registered names as choices, then every plug-in's own argument
        group (once per plug-in, even when it serves several names)."""
        names = self.names()
        parser.add_argument(
            self.option, choices=names, default=default, help=f"{self.what} (default: {default})"
        )
        seen: set[int] = set()
        for name in names:
            plugin: Any = self.get(name)
            if id(plugin) not in seen:
                seen.add(id(plugin))
                plugin.add_arguments(parser)
