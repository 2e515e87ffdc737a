import subprocess
import sys

import rmavatar
from rmavatar.commands import main


def test_version(capsys):
    try:
        main(["--version"])
    except SystemExit as exc:
        assert exc.code == 0
    assert rmavatar.__version__ in capsys.readouterr().out


def test_help_lists_commands():
    out = subprocess.run([sys.executable, "-m", "rmavatar", "--help"], capture_output=True, text=True, check=True)
    assert "usage: rmavatar" in out.stdout
