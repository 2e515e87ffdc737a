import os
import re
import subprocess
import sys

import pytest

import rmavatar
from rmavatar.commands import COMMANDS, main

# Every command the CLI has: removing one (or adding one without listing it here) fails the tests.
EXPECTED_COMMANDS = {"demo", "body", "inspect", "animate", "export", "view", "eval", "train", "render", "bench",
                     "synth", "capture", "batch", "reproduce"}


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """``python -m rmavatar ARGS`` with a wide terminal, so argparse wraps no help line."""
    env = {**os.environ, "COLUMNS": "1000"}
    return subprocess.run([sys.executable, "-m", "rmavatar", *args], capture_output=True, text=True, env=env,
                          timeout=120)


def test_version(capsys):
    try:
        main(["--version"])
    except SystemExit as exc:
        assert exc.code == 0
    assert rmavatar.__version__ in capsys.readouterr().out


def test_help_lists_commands():
    assert set(COMMANDS) == EXPECTED_COMMANDS
    out = run_cli("--help")
    assert out.returncode == 0, out.stderr
    assert "usage: rmavatar" in out.stdout
    # the commands' rows: the name indented by 4, then its help (on the next line after a long name)
    listed = re.findall(r"^ {4}(\S+)\s", out.stdout, re.M)
    assert sorted(listed) == sorted(EXPECTED_COMMANDS), out.stdout
    for name, (_, help_text) in COMMANDS.items():
        row = rf"^ {{4}}{re.escape(name)}\s+{re.escape(help_text)}$"
        assert re.search(row, out.stdout, re.M), (name, out.stdout)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_command_help(name):
    out = run_cli(name, "--help")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: rmavatar {name} "), out.stdout
    assert "-h, --help" in out.stdout
