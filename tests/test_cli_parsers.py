"""``zenswarm COMMAND ...`` builds only its own subcommand's parser (``compose/cli.py``'s table of
who registers what): it must parse and print ``--help`` exactly as the whole parser does, and it
must not import the other subcommands' modules (what makes a command start in a fraction of the
time the whole CLI takes)."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from zenswarm.compose import cli


def _subparsers(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return next(a.choices for a in p._actions if isinstance(a, argparse._SubParsersAction))


WHOLE = cli.build_parser()
COMMANDS = list(_subparsers(WHOLE))


def test_the_table_names_every_subcommand_once_in_the_whole_parser_s_order() -> None:
    table = list(cli._OWN) + [name for _, names in cli._MODULES for name in names]
    assert sorted(table) == sorted(COMMANDS), (table, COMMANDS)
    assert len(set(table)) == len(table), table
    assert [c for c in table if c in COMMANDS] == COMMANDS  # `zenswarm --help` lists them in this order


@pytest.mark.parametrize("command", COMMANDS)
def test_a_command_s_own_parser_prints_the_same_help_as_the_whole_parser(command: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "100")
    whole = _subparsers(cli.build_parser())[command]
    own = _subparsers(cli.build_parser(command))
    assert command in own, sorted(own)
    assert own[command].format_help() == whole.format_help()
    for nested, parser in _subparsers(whole).items() if any(isinstance(a, argparse._SubParsersAction) for a in whole._actions) else ():
        assert _subparsers(own[command])[nested].format_help() == parser.format_help(), nested


def test_an_unknown_command_is_refused_naming_every_command() -> None:
    r = subprocess.run([sys.executable, "-m", "zenswarm", "nosuch"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "invalid choice: 'nosuch'" in r.stderr and all(f"'{c}'" in r.stderr for c in COMMANDS), r.stderr


@pytest.mark.parametrize(
    ("argv", "absent"),
    [
        (["replay", "--help"], ["zenswarm.compose.supervisor", "zenswarm.bridge.vehicles.mavlink", "pymavlink",
                                "zenswarm.bridge.reports.report"]),
        (["verify", "--help"], ["zenswarm.bridge.replay.replay", "zenswarm.bridge.views.live", "zenswarm.bridge.reports.report"]),
        (["info", "--help"], ["zenswarm.compose.up", "zenswarm.bridge.replay.replay", "zenswarm.bridge.replay.verify", "cflib"]),
        (["up", "--help"], ["zenswarm.bridge.recording.info", "zenswarm.plant.mavlink_vehicle", "zenswarm.compose.plugcheck"]),
    ],
)
def test_a_command_imports_what_it_runs_not_the_whole_cli(argv: list[str], absent: list[str]) -> None:
    code = (
        "import sys, contextlib, io\n"
        "from zenswarm.compose.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n"
        f"        main({argv!r})\n"
        "    except SystemExit:\n"
        "        pass\n"
        f"print(sorted(m for m in {absent!r} if m in sys.modules))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stdout
