"""Every option of every subcommand says what it does (and its default), the README's command-line block is what
argparse prints, and ``organlab --version`` answers."""

from __future__ import annotations

import argparse
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

import organlab
from organlab.cli import main

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("cli_usage", ROOT / "docs" / "cli_usage.py")
cli_usage = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(cli_usage)
_TOP, SUBCOMMANDS = cli_usage.subcommands()


def _options(parser):
    return [a for a in parser._actions if not isinstance(a, (argparse._HelpAction, argparse._VersionAction))]


@pytest.mark.parametrize("name, parser", [(n, p) for n, _, p in SUBCOMMANDS], ids=[n for n, _, _ in SUBCOMMANDS])
def test_every_option_has_help_and_says_its_default(name, parser):
    assert [n for n, text, _ in SUBCOMMANDS if not text] == []  # each subcommand's one line in 'organlab --help'
    missing, silent = [], []
    for a in _options(parser):
        opt = "/".join(a.option_strings) or a.dest
        if not (a.help or "").strip():
            missing.append(opt)
        elif (a.default not in (None, False, argparse.SUPPRESS) and not isinstance(a, argparse._StoreTrueAction)
              and "default" not in a.help):
            silent.append(f"{opt} (default {a.default!r})")
    assert not missing, f"organlab {name}: options without help text: {missing}"
    assert not silent, f"organlab {name}: options whose help does not say their default: {silent}"


def test_readme_cli_block_is_what_argparse_prints():
    block = cli_usage.readme_block((ROOT / "README.md").read_text(encoding="utf-8"))
    assert block is not None, "README.md lost its cli-usage markers"
    assert block == cli_usage.block(), "README.md's command-line block is stale: run python docs/cli_usage.py"
    # every option of every subcommand is in it, each subcommand once
    for name, _, parser in SUBCOMMANDS:
        assert block.count(f"\norganlab {name} ") == 1, name
        for a in _options(parser):
            for opt in a.option_strings:
                if opt.startswith("--"):
                    assert opt in block, (name, opt)


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    version = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    assert capsys.readouterr().out.strip() == f"organlab {version}" == f"organlab {organlab.__version__}"


def test_version_from_the_installed_command():
    out = subprocess.run([sys.executable, "-m", "organlab", "--version"], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    assert out.strip() == f"organlab {organlab.__version__}"


#: What ``organlab --help`` may load: the package's light names and the ground floor the parser needs.
_HELP_LOADS = {"organlab", "organlab.cli", "organlab.cliparser", "organlab.lazy", "organlab.errors", "organlab.preflight",
               "organlab.progress", "organlab.session", "organlab.validate", "organlab.camera", "organlab.grid"}


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["reconstruct", "--help"], ["view", "--help"],
                                  ["sweep", "--help"], ["reconstruct", "--no-such-flag"]])
def test_help_loads_no_stage(argv):
    """issue 19: with every stage imported at the top, ``organlab --help`` took 5.5 s (numba, OpenCV, viser);
    the parser must build from the ground floor alone (the stages load when a command calls them)."""
    code = ("import sys\nfrom organlab.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            "print('LOADED', *sorted(m for m in sys.modules if m.split('.')[0] in "
            "('organlab', 'numba', 'cv2', 'scipy', 'skimage', 'pyvista', 'viser', 'dask', 'pymeshlab', 'pandas')), "
            "file=sys.stderr)\n")
    run = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=ROOT, check=True)
    loaded = set(run.stderr.split("LOADED")[-1].split())
    assert run.stdout or "error" in run.stderr  # it answered
    assert loaded - _HELP_LOADS == set(), f"organlab {' '.join(argv)} imported {sorted(loaded - _HELP_LOADS)}"


def test_the_program_exits_at_once_with_its_status_and_output(tmp_path):
    """issue 24: the interpreter's teardown after ``organlab reconstruct`` took 0.5 s idle (1.1-1.3 s under load)
    of a 4.9 s run; the program (``main()`` without arguments) now ends the process when the command is done. Its
    exit status, the output still in the pipes' buffers and the ``atexit`` handlers must survive that."""
    code = ("import atexit, sys\nfrom organlab.cli import main\n"
            "atexit.register(lambda: print('ATEXIT', file=sys.stderr))\nprint('BEFORE')\n"
            "sys.argv = ['organlab', 'reconstruct', sys.argv[1], '--out', sys.argv[2]]\n"
            "main()\nprint('NOT REACHED')\n")
    run = subprocess.run([sys.executable, "-c", code, str(tmp_path / "missing"), str(tmp_path / "out")],
                         capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 2
    assert run.stdout == "BEFORE\n"  # flushed from the pipe's buffer; nothing after main() ran
    assert "organlab: error:" in run.stderr and "session folder does not exist" in run.stderr
    assert run.stderr.rstrip().endswith("ATEXIT")
