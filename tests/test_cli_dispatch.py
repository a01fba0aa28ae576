"""The command line imports only the module of the command it runs (flockcal/cli.py `COMMANDS`): the table
must name, for every sub-command, the module that registers it, and a named command must parse as it does
with every module loaded."""

from __future__ import annotations

import subprocess
import sys

from flockcal.cli import COMMANDS, build_parser


def test_every_command_is_registered_by_the_module_the_table_names():
    parser = build_parser()
    assert set(parser.commands) == set(COMMANDS)
    for name, sub in parser.commands.items():
        assert sub.get_default("func").__module__ == COMMANDS[name], name


def test_a_named_command_parses_as_with_every_command_loaded():
    argv = ["fit", "take.npz", "--json", "--root", "pelvis", "--tolerance-mm", "3"]
    assert vars(build_parser("fit").parse_args(argv)) == vars(build_parser().parse_args(argv))


def test_running_one_command_imports_no_other_command_module(tmp_path):
    # `fit` of a missing file: it fails at once, after the parser was built; which modules were loaded?
    probe = ("import sys\nfrom flockcal.cli import main\n"
             f"code = main(['-v', 'fit', {str(tmp_path / 'none.npz')!r}])\n"
             "print(sorted(m for m in sys.modules if m.startswith('flockcal.commands.')))\n"
             "sys.exit(0 if code == 2 else 1)\n")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    loaded = set(eval(done.stdout.strip().splitlines()[-1]))
    others = {f"flockcal.commands.{m}" for m in ("simulate", "record", "serve", "markers", "batch")}
    assert not loaded & others, loaded
