"""The ``dyq`` command line: every subcommand (every entry of COMMANDS, those added later too) reports a
user's mistake in one line with exit code 2, never a traceback, and keeps the traceback of a bug."""
import argparse
import importlib
import subprocess
import sys

import pytest

from dyq.apps import cli, usage
from dyq.control.dispatch import DispatchConfig


def leaf_commands():
    """(argv prefix, parser) of every runnable (sub)command, or (argv prefix, None) when importing the
    command fails for a missing third-party package (reported by the CLI itself)."""
    leaves = []

    def walk(prefix, parser):
        sub = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not sub:
            leaves.append((prefix, parser))
        for action in sub:
            for name, child in action.choices.items():
                walk(prefix + [name], child)

    for name, (module, _) in cli.COMMANDS.items():
        parser = usage.ArgumentParser(prog=f"dyq {name}")
        try:
            importlib.import_module(module).add_arguments(parser)
        except ModuleNotFoundError:
            leaves.append(([name], None))
            continue
        walk([name], parser)
    return leaves


LEAVES = leaf_commands()


def run(argv, capsys):
    """(exit code, stderr) of `dyq ARGV`, in process."""
    code = cli.main(argv)
    return code, capsys.readouterr().err


def assert_one_line_error(code, err, argv):
    assert code == 2, (argv, code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and "Traceback" not in err, (argv, err)


def bad_values(action, folder):
    """Values of one argument that its command must reject."""
    if getattr(action.type, "invalid_examples", None):
        return action.type.invalid_examples(folder)
    if action.type in (int, float):
        return ["not-a-number"]
    if action.choices and not isinstance(action, argparse._SubParsersAction):
        return ["not-a-choice"]
    return []


@pytest.mark.parametrize("prefix,parser", LEAVES, ids=[" ".join(p) for p, _ in LEAVES])
def test_unknown_option_is_one_line_exit_2(prefix, parser, capsys):
    assert_one_line_error(*run(prefix + ["--no-such-option"], capsys), prefix)


@pytest.mark.parametrize("prefix,parser", LEAVES, ids=[" ".join(p) for p, _ in LEAVES])
def test_every_bad_argument_is_one_line_exit_2(prefix, parser, tmp_path, capsys):
    if parser is None:
        pytest.skip("command not importable here (reported in one line by test_unknown_option)")
    first_positional = next((a for a in parser._actions if not a.option_strings), None)
    tried = 0
    for action in parser._actions:
        if action.option_strings and action.option_strings[0] == "-h":
            continue
        for value in bad_values(action, tmp_path):
            if action.option_strings:
                argv = prefix + [action.option_strings[-1], value]
            elif action is first_positional:
                argv = prefix + [value]
            else:
                continue
            assert_one_line_error(*run(argv, capsys), argv)
            tried += 1
    if any(a.required for a in parser._actions):
        assert_one_line_error(*run(prefix, capsys), prefix)  # nothing given


def test_python_m_dyq_runs_the_command_and_names_subcommands():
    out = subprocess.run([sys.executable, "-m", "dyq", "dispatch", "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert out.startswith("usage: dyq dispatch ")
    replay = subprocess.run([sys.executable, "-m", "dyq", "dispatch", "replay", "--help"], capture_output=True,
                            text=True, check=True).stdout
    assert replay.startswith("usage: dyq dispatch replay ")


@pytest.mark.parametrize("content", [b"PK\x03\x04truncated", b"\x93NUMPY\x01\x00garbage"])
def test_replay_of_a_truncated_or_wrong_kind_file_is_one_line(tmp_path, capsys, content):
    broken = tmp_path / "broken.npz"
    broken.write_bytes(content)
    assert_one_line_error(*run(["dispatch", "replay", str(broken)], capsys), broken)


def test_replay_of_a_malformed_config_is_one_line(tmp_path, capsys):
    trajectory, config = tmp_path / "traj.npz", tmp_path / "cfg.json"
    assert cli.main(["dispatch", "demo", str(trajectory)]) == 0
    config.write_text('{"no_such_field": 1}')
    capsys.readouterr()
    assert_one_line_error(*run(["dispatch", "replay", str(trajectory), "--config", str(config)], capsys), config)


def test_missing_optional_dependency_is_one_line(tmp_path, capsys, monkeypatch):
    trajectory = tmp_path / "traj.npz"
    assert cli.main(["dispatch", "demo", str(trajectory)]) == 0
    capsys.readouterr()
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    code, err = run(["dispatch", "replay", str(trajectory), "--out", str(tmp_path / "plot.png")], capsys)
    assert_one_line_error(code, err, "replay --out")
    assert "matplotlib" in err


def test_a_damaged_file_found_deep_in_a_command_is_one_line(tmp_path, monkeypatch, capsys):
    # A FileFormatError names the user's file wherever it is raised: the checkpoint, dispatch config, results
    # and episode files that eval, demo, profile and calibrate read through library code.
    from dyq.apps import dispatch_cli

    config = tmp_path / "dispatch.json"
    config.write_text('{"K": "three"')
    monkeypatch.setattr(dispatch_cli, "main", lambda args: DispatchConfig.load(config))
    code, err = run(["dispatch", "config", str(tmp_path / "cfg.json")], capsys)
    assert_one_line_error(code, err, "dispatch config")
    assert "dispatch.json" in err


def test_a_bug_keeps_its_traceback(monkeypatch):
    from dyq.apps import dispatch_cli

    def broken(args):
        return int("a bug deep down")  # a ValueError raised outside the command's own module

    monkeypatch.setattr(dispatch_cli, "main", lambda args: broken(args))
    monkeypatch.setattr(dispatch_cli, "__file__", usage.__file__)
    with pytest.raises(ValueError):
        cli.main(["dispatch", "config", "cfg.json"])
