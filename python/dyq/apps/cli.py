"""The ``dyq`` command: one table of subcommands, each a module with ``add_arguments(parser)`` and
``main(args) -> int``, imported only when its command runs (``dyq demo`` needs transformers,
``dyq dispatch`` does not). A new command is one entry of :data:`COMMANDS`."""
from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("dyq.apps.demo", "a trained robot policy in closed loop: DyQ against fp32 (needs the sim extra)"),
    "dispatch": ("dyq.apps.dispatch_cli", "dispatcher tools: replay a trajectory, write a demo trajectory or config"),
    "collect": ("dyq.sim.demos", "scripted-expert demonstrations for a task, in robomimic's HDF5 layout"),
    "train": ("dyq.sim.train", "behavior-clone a robot policy on demonstrations (robomimic HDF5)"),
    "eval": ("dyq.sim.evaluate", "closed-loop evaluation: task x configuration x seed grid, cached and resumable"),
    "profile": ("dyq.sim.profile", "step-wise perturbation profile of a task's policy; proxy correlations (Sec. III)"),
    "calibrate": ("dyq.sim.profile", "calibrate the dispatcher (lambda, Theta, K, theta_fp) on calibration seeds"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="dyq", description="Dynamic-precision INT4 inference for VLA policies")
    commands = parser.add_subparsers(dest="command", required=True)
    for name, (module, help_text) in COMMANDS.items():
        command = commands.add_parser(name, help=help_text)
        if argv[:1] == [name]:
            importlib.import_module(module).add_arguments(command)
    args = parser.parse_args(argv)
    return importlib.import_module(COMMANDS[args.command][0]).main(args)
