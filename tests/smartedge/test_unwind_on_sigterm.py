"""A command stopped by SIGTERM (a supervisor, ``kill``) or SIGHUP (a closed terminal) unwinds:
its ``finally`` blocks run, so a benchmark or the demo stops the processes it started instead
of leaving them behind (smartedge.commands.unwind_on_sigterm, installed by every command)."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

CHILD = """
import signal, time
from smartedge.commands import unwind_on_sigterm
# as started from a terminal (a test run under nohup inherits SIGHUP ignored)
signal.signal(signal.SIGHUP, signal.SIG_DFL)
unwind_on_sigterm()
try:
    print("ready", flush=True)
    time.sleep(30)
finally:
    print("cleaned up", flush=True)
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_signalled_command_runs_its_finally_blocks(sig: signal.Signals) -> None:
    proc = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=20)
    assert "cleaned up" in out
    assert proc.returncode == 128 + int(sig)


def test_a_handler_already_installed_or_an_ignored_signal_is_kept() -> None:
    # a handler of the program's own, and SIGHUP ignored by nohup, stay as they are
    code = ("import signal\n"
            "from smartedge.commands import unwind_on_sigterm\n"
            "mine = lambda *a: None\n"
            "signal.signal(signal.SIGTERM, mine)\n"
            "signal.signal(signal.SIGHUP, signal.SIG_IGN)\n"
            "unwind_on_sigterm()\n"
            "assert signal.getsignal(signal.SIGTERM) is mine\n"
            "assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=20)
