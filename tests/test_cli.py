"""The assembled ``mavispm`` command line."""

from __future__ import annotations

import importlib

import pytest

from mavispm.workflows import cli


@pytest.mark.parametrize("group, module", cli.COMMAND_MODULES)
def test_every_stage_module_provides_a_command(group, module):
    mod = importlib.import_module(module)
    assert callable(mod.register)


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in ("simulate", "measure", "dynamics", "run", "report"):
        assert name in out
    with pytest.raises(SystemExit):
        cli.main(["simulate", "--help"])
    out = capsys.readouterr().out
    for name in ("cluster", "optics", "frames"):
        assert name in out
    with pytest.raises(SystemExit):
        cli.main(["measure", "--help"])
    out = capsys.readouterr().out
    for name in ("stars", "propermotions"):
        assert name in out


def test_user_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    missing = tmp_path / "missing.h5"
    code = cli.main(
        ["measure", "propermotions", str(missing), str(missing), "-o", str(tmp_path / "pm.h5")]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "missing.h5" in err and "Traceback" not in err
    assert not (tmp_path / "pm.h5").exists()


def _commands_of(parser):
    """(group, name) of every command of an assembled parser."""
    import argparse

    found = set()
    top = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in top.choices.items():
        inner = [a for a in sub._actions if isinstance(a, argparse._SubParsersAction)]
        if name in cli.GROUP_HELP and inner:
            found |= {(name, cmd) for cmd in inner[0].choices}
        else:
            found.add((None, name))
    return found


def test_command_table_names_every_registered_command():
    """The lazy table must list exactly what the modules register (or commands go missing)."""
    assert _commands_of(cli.build_parser()) == set(cli.COMMANDS)
    for (group, name), module in cli.COMMANDS.items():
        argv = [group, name] if group else [name]
        assert cli.modules_for(argv) == [(group, module)]
        assert (group, name) in _commands_of(cli.build_parser(argv, everything=False))
    assert cli.modules_for(["--help"]) == cli.COMMAND_MODULES
    assert cli.modules_for(["simulate", "--help"]) == cli.COMMAND_MODULES


def test_one_command_imports_only_its_own_stage():
    import subprocess
    import sys

    code = (
        "import sys; from mavispm.workflows import cli\n"
        "try:\n    cli.main(['simulate', 'frames', '--help'])\n"
        "except SystemExit:\n    pass\n"
        "print(sorted(m for m in sys.modules if m.startswith('mavispm.measure')"
        " or m.startswith('mavispm.dynamics') or m == 'matplotlib.pyplot'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "--scene" in out.stdout
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_only_the_program_freezes_its_imports_out_of_the_collector():
    """``main(argv)`` called from Python leaves the caller's garbage collector alone; the
    program (``main()`` reading ``sys.argv``) freezes the objects of its imports."""
    import subprocess
    import sys

    code = (
        "import gc, sys; from mavispm.workflows import cli\n"
        "before = gc.get_freeze_count()\n"
        "assert cli.main(['simulate']) == 0\n"
        "called = gc.get_freeze_count()\n"
        "sys.argv = ['mavispm', 'simulate']\n"
        "assert cli.main() == 0\n"
        "print(before, called, gc.get_freeze_count() > 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "0 0 True"
