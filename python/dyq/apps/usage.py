"""User mistakes on the ``dyq`` command line: one line on stderr and exit code 2, never a traceback.

For command authors (a command is a module with ``add_arguments(parser)`` and ``main(args) -> int``,
one entry of ``dyq.apps.cli.COMMANDS``):

- Give every argument a type from here (:func:`positive_int`, :func:`input_file`, :func:`output_file`,
  ...): argparse then rejects a bad value, a missing, empty or wrong-kind file and an unwritable output
  path in one line before ``main`` runs.
- Raise :class:`UsageError` for what only ``main`` can tell (a file that does not parse, a combination of
  arguments), and call :func:`require` for an optional dependency.
- Without that, :func:`user_error_message` still reports in one line an OSError about a path given on
  the command line, a missing third-party package, and a ValueError raised in the command's own module
  (its checks of its arguments). Anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import argparse
import importlib
import math
import os
import traceback
from pathlib import Path
from types import ModuleType
from typing import Callable, Sequence

from ..errors import FileFormatError

# Every type here carries invalid_examples(folder) -> command-line values it rejects (files made in
# `folder`), so that tests/test_cli.py can try each one on every argument of every command.


class UsageError(Exception):
    """A mistake in the command line or in a file it names: reported in one line, exit code 2."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse, with its errors in one line (``dyq dispatch replay: error: ...``) instead of usage + error."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def int_at_least(minimum: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    parse.invalid_examples = lambda folder: ["not-a-number", str(minimum - 1)]
    return parse


positive_int = int_at_least(1)
nonnegative_int = int_at_least(0)


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


positive_float.invalid_examples = lambda folder: ["not-a-number", "0", "nan"]


def nonnegative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


nonnegative_float.invalid_examples = lambda folder: ["not-a-number", "-0.5", "nan", "inf"]


def comma_list(choices: Sequence[str]) -> Callable[[str], list[str]]:
    """A comma-separated list of names, each one of ``choices`` (empty items are dropped)."""
    def parse(text: str) -> list[str]:
        names = [name for name in text.split(",") if name]
        unknown = [name for name in names if name not in choices]
        if unknown or not names:
            raise argparse.ArgumentTypeError(f"unknown {', '.join(map(repr, unknown)) or 'empty list'}; choose "
                                             f"comma-separated names from {', '.join(choices)}")
        return names

    parse.invalid_examples = lambda folder: ["not-a-choice", f"{choices[0]},not-a-choice", ","]
    return parse


def name_equals_folder(choices: Sequence[str]) -> Callable[[str], tuple[str, Path]]:
    """``NAME=DIR``: a name of ``choices`` and an existing folder."""
    def parse(text: str) -> tuple[str, Path]:
        name, equals, folder = text.partition("=")
        if not equals or not folder:
            raise argparse.ArgumentTypeError(f"expected NAME=DIR, got {text!r}")
        if name not in choices:
            raise argparse.ArgumentTypeError(f"unknown {name!r} in {text!r}; choose from {', '.join(choices)}")
        return name, input_dir(folder)

    parse.invalid_examples = lambda folder: ["no-equals-sign", f"not-a-choice={folder}",
                                             f"{choices[0]}={folder / 'missing'}", f"{choices[0]}="]
    return parse


def _check_suffix(text: str, suffixes: tuple[str, ...]) -> None:
    if suffixes and Path(text).suffix.lower() not in suffixes:
        raise argparse.ArgumentTypeError(f"{text}: expected a {' or '.join(suffixes)} file")


def input_file(*suffixes: str) -> Callable[[str], Path]:
    """An existing, readable, non-empty file, with one of ``suffixes`` (any when none are given)."""

    def parse(text: str) -> Path:
        path = Path(text)
        _check_suffix(text, suffixes)
        if not path.exists():
            raise argparse.ArgumentTypeError(f"{text}: no such file")
        if not path.is_file():
            raise argparse.ArgumentTypeError(f"{text}: not a file")
        if not os.access(path, os.R_OK):
            raise argparse.ArgumentTypeError(f"{text}: not readable")
        if path.stat().st_size == 0:
            raise argparse.ArgumentTypeError(f"{text}: empty file")
        return path

    def invalid_examples(folder: Path) -> list[str]:
        suffix = suffixes[0] if suffixes else ".dat"
        empty = folder / f"empty{suffix}"
        empty.touch()
        wrong_kind = folder / "wrong-kind.txt"
        wrong_kind.write_text("text")
        examples = [str(folder / f"missing{suffix}"), str(empty), str(folder)]
        return examples + ([str(wrong_kind)] if suffixes else [])

    parse.invalid_examples = invalid_examples
    return parse


def input_dir(text: str) -> Path:
    path = Path(text)
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no such folder")
    return path


input_dir.invalid_examples = lambda folder: [str(folder / "missing")]


def _check_writable_folder(text: str, folder: Path) -> None:
    existing = folder
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: cannot write under {existing}")


def output_file(*suffixes: str) -> Callable[[str], Path]:
    """A file that can be written: its folder exists and is writable, and it is no folder itself."""

    def parse(text: str) -> Path:
        path = Path(text)
        _check_suffix(text, suffixes)
        if path.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: is a folder")
        if not path.parent.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: no folder {path.parent}")
        if (path.exists() and not os.access(path, os.W_OK)) or not os.access(path.parent, os.W_OK | os.X_OK):
            raise argparse.ArgumentTypeError(f"{text}: not writable")
        return path

    def invalid_examples(folder: Path) -> list[str]:
        suffix = suffixes[0] if suffixes else ".out"
        a_file = folder / "a-file.txt"
        a_file.write_text("text")
        examples = [str(folder / "missing-folder" / f"out{suffix}"), str(a_file / f"out{suffix}")]
        return examples + ([str(folder / "out.wrong-kind")] if suffixes else [])

    parse.invalid_examples = invalid_examples
    return parse


def output_dir(text: str) -> Path:
    """A folder that exists or can be created."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: not a folder")
    _check_writable_folder(text, path)
    return path


def _file_in_the_way(folder: Path) -> list[str]:
    a_file = folder / "a-file.txt"
    a_file.write_text("text")
    return [str(a_file), str(a_file / "below")]


output_dir.invalid_examples = _file_in_the_way


def require(module: str, purpose: str, package: str | None = None) -> ModuleType:
    """Import an optional dependency, or raise UsageError naming what needs it and how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise UsageError(f"{purpose} needs {module}: pip install {package or module}") from None


def _paths_given(args: argparse.Namespace | None) -> set[str]:
    values = []
    for value in vars(args or argparse.Namespace()).values():
        values.extend(value if isinstance(value, (list, tuple)) else [value])
    return {os.fspath(v) for v in values if isinstance(v, (str, os.PathLike))}


def user_error_message(error: BaseException, args: argparse.Namespace | None, command: ModuleType | None) -> str | None:
    """The one-line report of ``error`` raised by ``command.main(args)`` (or by importing the command, with
    args and command None) if it is the user's mistake, else None (a bug, whose traceback must show)."""
    if isinstance(error, (UsageError, FileFormatError)):
        return str(error)
    if isinstance(error, OSError) and error.filename is not None and os.fspath(error.filename) in _paths_given(args):
        return f"{error.filename}: {error.strerror or error}"
    if isinstance(error, ModuleNotFoundError) and error.name and error.name.partition(".")[0] != "dyq":
        package = error.name.partition(".")[0]
        return f"needs the Python package {package}, which is not installed (pip install {package})"
    if isinstance(error, ValueError) and command is not None and error.__traceback__ is not None:
        raised_in = traceback.extract_tb(error.__traceback__)[-1].filename
        # A frame of compiled or frozen code names no file on disk (numpy's "bit_generator.pyx").
        if command.__file__ and os.path.isfile(raised_in) and os.path.samefile(raised_in, command.__file__):
            return str(error)
    return None
