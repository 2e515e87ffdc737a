"""Every command's output options go through the one output rule (:mod:`rmavatar.utils.outputs`).

The walk reads every command's parser (sub-commands included) and finds each option that names
something rmavatar writes; each must have a case below. Each case puts the user's own file (or a
folder holding the user's file) where that output goes and runs the command: it must be refused with
exit code 2, before any long work, and the user's file must be left exactly as it was. A new output
option without a case here fails ``test_every_output_option_has_a_case``.
"""

from __future__ import annotations

import argparse
import importlib
import re
from pathlib import Path

import numpy as np
import pytest

from rmavatar.commands import COMMANDS, main

# Option names that are outputs wherever they appear, and help texts that say an option is written.
OUTPUT_DESTS = {"out", "json", "images", "work", "write_jobs", "overlay", "ply", "png"}
OUTPUT_HELP = re.compile(r"^(output|also write|write |where to write|folder for|batch folder|the dataset folder "
                         r"to write|run folder to create|an \.mp4)", re.I)
# Options caught by the names above that are read, not written.
NOT_OUTPUTS = {("render", "--ply")}
PRECIOUS = "the user's own file\n"


def output_options() -> set[tuple[str, str]]:
    """(command, option) for every option of every command that names something rmavatar writes."""
    found = set()

    def walk(prefix: str, parser: argparse.ArgumentParser) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(f"{prefix} {name}", sub)
                continue
            if action.nargs == 0 or action.type in (int, float):
                continue  # flags and numbers name nothing
            option = action.option_strings[0] if action.option_strings else action.dest
            if action.dest in OUTPUT_DESTS or OUTPUT_HELP.match(action.help or ""):
                found.add((prefix, option))

    for name, (module, _) in COMMANDS.items():
        parser = argparse.ArgumentParser(prog=f"rmavatar {name}")
        importlib.import_module(module).add_arguments(parser)
        walk(name, parser)
    return found - NOT_OUTPUTS


def _file(tmp: Path, name: str) -> Path:
    path = tmp / name
    path.write_text(PRECIOUS)
    return path


def _folder(tmp: Path, name: str) -> Path:
    path = tmp / name
    path.mkdir(parents=True)
    (path / "keep.txt").write_text(PRECIOUS)
    return path


def _motion(tmp: Path) -> str:
    path = tmp / "motion.npz"
    np.savez(path, poses=np.zeros((2, 72), np.float32))
    return str(path)


def _data(tmp: Path) -> str:
    path = tmp / "data"
    (path / "images").mkdir(parents=True)
    (path / "meta.yaml").write_text("name: d\n")
    return str(path)


def _frames(tmp: Path) -> str:
    import imageio.v2 as imageio

    path = tmp / "frames"
    path.mkdir()
    for i in range(3):
        imageio.imwrite(path / f"{i:03d}.png", np.full((16, 16, 3), 128, np.uint8))
    return str(path)


def _jobs(tmp: Path) -> str:
    path = tmp / "jobs.yaml"
    path.write_text(f"jobs:\n  - {{name: a, data: {_data(tmp)}, overrides: {{iters: 1}}}}\n")
    return str(path)


def _ps(tmp: Path) -> str:
    (tmp / "ps" / "male-3-casual").mkdir(parents=True)
    return str(tmp / "ps")


# (command, option) -> a function of tmp_path giving (argv, the user's file that must survive).
CASES = {
    ("demo", "--out"): lambda t: (["demo", "--out", str(_folder(t, "o"))], t / "o" / "keep.txt"),
    ("body show", "--out"): lambda t: (["body", "show", "--out", str(_file(t, "b.png"))], t / "b.png"),
    ("inspect", "--json"): lambda t: (["inspect", _data(t), "--json", str(_file(t, "s.json"))], t / "s.json"),
    ("inspect", "--overlay"): lambda t: (["inspect", _data(t), "--overlay", str(_file(t, "s.png"))], t / "s.png"),
    ("animate", "--out"): lambda t: (["animate", str(t / "run"), "--motion", _motion(t), "--out",
                                      str(_file(t, "a.mp4"))], t / "a.mp4"),
    ("export", "--ply"): lambda t: (["export", str(t / "run"), "--ply", str(_file(t, "a.ply"))], t / "a.ply"),
    ("eval", "--json"): lambda t: (["eval", str(t / "run"), "--json", str(_file(t, "e.json"))], t / "e.json"),
    ("eval", "--images"): lambda t: (["eval", str(t / "run"), "--json", str(t / "e.json"), "--images",
                                      str(_folder(t, "imgs"))], t / "imgs" / "keep.txt"),
    ("train", "--out"): lambda t: (["train", _data(t), "--out", str(_folder(t, "run"))], t / "run" / "keep.txt"),
    ("render", "--out"): lambda t: (["render", "--random", "10", "--out", str(_file(t, "r.png"))], t / "r.png"),
    ("bench raster", "--json"): lambda t: (["bench", "raster", "--json", str(_file(t, "b.json"))], t / "b.json"),
    ("bench quality", "--json"): lambda t: (["bench", "quality", "--json", str(_file(t, "b.json"))], t / "b.json"),
    ("bench quality", "--work"): lambda t: (["bench", "quality", "--json", str(t / "q.json"), "--size", "32",
                                             "--iters", "1", "--variants", "full", "--work", str(t / "w")],
                                            _folder(t, "w/synth-seed0-32") / "keep.txt"),
    ("bench step", "--json"): lambda t: (["bench", "step", "--json", str(_file(t, "b.json"))], t / "b.json"),
    ("bench speed", "--json"): lambda t: (["bench", "speed", "--json", str(_file(t, "b.json"))], t / "b.json"),
    ("bench avatar", "--json"): lambda t: (["bench", "avatar", "--json", str(_file(t, "b.json"))], t / "b.json"),
    ("bench render", "--json"): lambda t: (["bench", "render", str(t / "run"), "--json", str(_file(t, "b.json"))],
                                           t / "b.json"),
    ("bench capture", "--json"): lambda t: (["bench", "capture", "--json", str(_file(t, "b.json"))], t / "b.json"),
    ("bench capture", "--work"): lambda t: (["bench", "capture", "--json", str(t / "c.json"), "--work", str(t / "w")],
                                            _folder(t, "w/captured") / "keep.txt"),
    ("synth", "out"): lambda t: (["synth", str(_folder(t, "s"))], t / "s" / "keep.txt"),
    ("capture", "--out"): lambda t: (["capture", _frames(t), "--out", str(_folder(t, "c"))], t / "c" / "keep.txt"),
    ("batch", "--out"): lambda t: (["batch", _jobs(t), "--out", str(_folder(t, "root"))], t / "root" / "keep.txt"),
    ("reproduce", "--out"): lambda t: (["reproduce", "paper", "--people-snapshot", _ps(t), "--body", "anny",
                                        "--tables", "1", "--subjects", "male-3-casual", "--out",
                                        str(_folder(t, "root"))], t / "root" / "keep.txt"),
    ("reproduce", "--write-jobs"): lambda t: (["reproduce", "paper", "--people-snapshot", _ps(t), "--body", "anny",
                                               "--tables", "1", "--subjects", "male-3-casual", "--out",
                                               str(t / "root"), "--write-jobs", str(_file(t, "j.yaml"))],
                                              t / "j.yaml"),
}


def test_every_output_option_has_a_case():
    found = output_options()
    assert found - set(CASES) == set(), "output options without a case in CASES (add one)"
    assert set(CASES) - found == set(), "cases for options that are gone or no longer found by the walk"


@pytest.mark.parametrize("case", sorted(CASES), ids=lambda c: f"{c[0]} {c[1]}".replace(" ", "_"))
def test_output_never_replaces_the_users_file(case, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("RMAVATAR_CACHE", str(tmp_path / "cache"))
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    argv, precious = CASES[case](tmp_path)
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, f"{case}: exit code {code}, stderr: {err[-600:]}"
    assert re.search(r"refus|did not write|not empty|holds no rmavatar|not an rmavatar run|holds files", err), err
    assert precious.read_text() == PRECIOUS
    # Nothing else was made beside it: no half-written output, no temporary left.
    assert not any(p.name.startswith(".") and p.name.endswith(".tmp") for p in precious.parent.iterdir())
