"""The ``prt`` command. Thin: each subcommand lives in its own module of this package and only
calls the library modules.

A subcommand module defines ``register(subparsers)``, which adds its parser and sets
``func=run`` on it via ``set_defaults``. ``run(args) -> int`` returns the exit status. Bad
input ends with one line and status 2; Ctrl-C ends quietly with status 130 and, where the
command set ``args.resume_hint`` before its long work, says what was kept and how to continue.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# Order here is the order in ``prt --help``.
COMMANDS = ["bench", "precompute", "compress", "light", "info", "render", "plot", "validate"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="prt",
        description="prt_torch: precomputed radiance transfer and its compression",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__name__}.{name}":  # subcommand not part of this build
                continue
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        if args.command is None and "bench" in parser._subparsers._group_actions[0].choices:  # type: ignore[union-attr]
            # `prt` alone behaves as `prt bench` (the default benchmark).
            return main(["bench", *(argv or [])])
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:  # `prt ... | head`: the reader left; not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        if getattr(args, "debug", False):
            raise
        hint = getattr(args, "resume_hint", None)
        print(f"prt {args.command}: interrupted" + (f"; {hint}" if hint else ""), file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError, FileExistsError, TypeError, OSError) as e:
        if getattr(args, "debug", False):
            raise
        print(f"prt {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
