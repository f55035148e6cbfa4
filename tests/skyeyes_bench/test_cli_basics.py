"""CLI front: --help lists the groups, builds without heavy imports, exit codes."""

import subprocess
import sys

import pytest
from conftest import ROOT, run_cli

from skyeyes_bench import cli


def test_help_lists_subcommands():
    _, out, _ = run_cli("--help")
    for name in cli.COMMANDS:
        assert f"\n    {name}" in out, name
    _, out, _ = run_cli("data", "--help")
    for action in ("check", "import-carla", "import-matrixcity"):
        assert action in out


def test_one_module_per_command_with_register_and_run():
    import argparse
    import importlib

    parser = cli.build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert list(commands) == cli.COMMANDS
    for name in cli.COMMANDS:
        module = importlib.import_module(f"skyeyes_bench.commands.{name}")
        assert callable(module.register) and commands[name].get_default("run") is module.run, name
        groups = [a for a in commands[name]._actions if isinstance(a, argparse._SubParsersAction)]
        if groups:  # a group: every action it registers has its function, and no other
            assert set(groups[0].choices) == set(module.ACTIONS), name


def test_a_command_module_that_fails_to_import_is_an_error(monkeypatch):
    monkeypatch.setattr(cli, "COMMANDS", [*cli.COMMANDS, "no-such-command"])
    with pytest.raises(ModuleNotFoundError, match="no-such-command"):
        cli.build_parser()


def test_parser_builds_without_heavy_imports():
    code = (
        "import sys\n"
        "from skyeyes_bench.cli import build_parser\n"
        "p = build_parser()\n"
        "heavy = [m for m in ('torch', 'numpy', 'OpenImageIO', 'scipy', 'diffusers', 'reference') if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"heavy modules imported while building the parser: {r.stdout}"


def test_help_subprocess_exit_codes():
    r = subprocess.run([sys.executable, "-m", "skyeyes_bench.cli", "--help"], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert r.returncode == 0 and "subcommands" in r.stdout
    r = subprocess.run([sys.executable, "-m", "skyeyes_bench.cli", "frobnicate"], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "invalid choice" in r.stderr


def test_usage_errors_exit_2():
    rc, _, err = run_cli("protocols", "show", check=2)  # missing argument
    assert "the following arguments are required" in err and err.count("\n") == 1
    rc, out, _ = run_cli("protocols", check=2)  # group without an action: its help
    assert "list" in out and "show" in out
    run_cli("--version", check=0)


def test_data_presets_are_synthtowns():
    from skyeyes_bench.commands import data
    from skyeyes_bench.data.synthtown import PRESETS

    assert set(data._PRESETS) == set(PRESETS)  # listed by hand so that --help stays light
