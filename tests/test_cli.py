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
