"""The ``dyq`` command: ``dyq demo`` (the main job) and ``dyq dispatch ...`` (dispatcher tools)."""
from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="dyq", description="Dynamic-precision INT4 inference for VLA policies")
    commands = parser.add_subparsers(dest="command", required=True)
    from . import demo

    demo_parser = commands.add_parser("demo", help="quantize a small OpenVLA-shaped policy and run a control loop")
    demo.add_arguments(demo_parser)
    commands.add_parser("dispatch", help="dispatcher tools: replay a trajectory, write a demo trajectory or config",
                        add_help=False)
    if argv[:1] == ["dispatch"]:
        from . import dispatch_cli

        return dispatch_cli.main(argv[1:])
    args = parser.parse_args(argv)
    return demo.main(args)


if __name__ == "__main__":
    sys.exit(main())
