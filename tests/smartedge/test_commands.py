"""The lazy subcommand registry both ``smartedge`` and ``smartedge bench`` dispatch through."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from lab.bench import BENCHES
from smartedge.cli import all_commands
from smartedge.commands import EXIT_UNAVAILABLE, Command, run_command


def test_every_registered_command_names_a_module_and_help() -> None:
    for table in (all_commands(), BENCHES):
        for name, command in table.items():
            assert isinstance(command, Command), name
            assert command.module and command.function.isidentifier() and command.help


def test_runs_the_function_with_the_remaining_arguments(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "fake_command.py").write_text(
        "def main(argv):\n    return len(argv)\n\ndef quiet(argv):\n    return None\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert run_command("smartedge fake", Command("fake_command", "main", "-"), ["a", "b"]) == 2
    assert run_command("smartedge fake", Command("fake_command", "quiet", "-"), []) == 0
    sys.modules.pop("fake_command", None)


def test_a_missing_module_or_dependency_is_one_line(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    code = run_command("smartedge nope", Command("smartedge.no_such_command", "main", "-"), [])
    assert code == EXIT_UNAVAILABLE
    assert capsys.readouterr().err == "smartedge nope: not available in this version\n"
    (tmp_path / "needs_extra.py").write_text("import no_such_dependency_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    code = run_command("smartedge bench x", Command("needs_extra", "main", "-"), [])
    assert code == EXIT_UNAVAILABLE
    err = capsys.readouterr().err
    assert err.startswith("smartedge bench x: missing dependency 'no_such_dependency_xyz'")
