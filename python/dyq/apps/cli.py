"""The ``dyq`` command: one table of subcommands, each a module with ``add_arguments(parser)`` and
``main(args) -> int``, imported only when its command runs (``dyq demo`` needs transformers,
``dyq dispatch`` does not). A new command is one entry of :data:`COMMANDS`; how it reports a user's
mistakes (one line, exit code 2) is in :mod:`dyq.apps.usage`.
"""
from __future__ import annotations

import importlib
import sys

from .usage import ArgumentParser, user_error_message

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("dyq.apps.demo", "a trained robot policy in closed loop: DyQ against fp32 (needs the sim extra)"),
    "dispatch": ("dyq.apps.dispatch_cli", "dispatcher tools: replay a trajectory, write a demo trajectory or config"),
    "collect": ("dyq.sim.demos", "scripted-expert demonstrations for a task, in robomimic's HDF5 layout"),
    "train": ("dyq.sim.train", "behavior-clone a robot policy on demonstrations (robomimic HDF5)"),
    "eval": ("dyq.sim.evaluate", "closed-loop evaluation: task x configuration x seed grid, cached and resumable"),
    "profile": ("dyq.sim.profile", "step-wise perturbation profile of a task's policy; proxy correlations (Sec. III)"),
    "calibrate": ("dyq.sim.profile", "calibrate the dispatcher (lambda, Theta, K, theta_fp) on calibration seeds"),
    "quantize": ("dyq.apps.quantize_cli", "convert a local Hugging Face checkpoint to INT4 weights, for from_pretrained"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = ArgumentParser(prog="dyq", description="Dynamic-precision INT4 inference for VLA policies")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    for name, (module, help_text) in COMMANDS.items():
        subparser = commands.add_parser(name, help=help_text, prog=f"dyq {name}")
        if argv[:1] == [name]:
            try:
                importlib.import_module(module).add_arguments(subparser)
            except ModuleNotFoundError as error:
                return _report(name, error, None, None)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit:  # --help, or a bad argument already reported in one line
        return exit.code
    command = importlib.import_module(COMMANDS[args.command][0])
    try:
        return command.main(args)
    except Exception as error:
        return _report(args.command, error, args, command)


def _report(name: str, error: Exception, args, command) -> int:
    """Print a user's mistake in one line and return 2; re-raise anything else (a bug)."""
    message = user_error_message(error, args, command)
    if message is None:
        raise error
    print(f"dyq {name}: error: {message}", file=sys.stderr)
    return 2
