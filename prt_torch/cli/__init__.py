"""The ``prt`` command. Thin: each subcommand lives in its own module of this package and only
calls the library modules.

A subcommand module defines ``register(subparsers)``, which adds its parser and sets
``func=run`` on it via ``set_defaults``. ``run(args) -> int`` returns the exit status. Bad
input ends with one line and status 2; Ctrl-C ends quietly with status 130, SIGTERM (what
``timeout``, batch schedulers and ``kill`` send) with 143, and both, where the command set
``args.resume_hint`` before its long work, say what was kept and how to continue. A warning is
one line, ``prt <command>: warning: ...`` (the library keeps raising Python warnings for library
users). Options may come anywhere: ``key=value`` overrides after an option still count as
overrides (``prt bench CONFIG --dry-run key=value``).
"""
from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
import warnings

# Order here is the order in ``prt --help``.
COMMANDS = ["bench", "precompute", "compress", "light", "info", "render", "relight", "plot", "validate", "shrm", "invert"]


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
    for p in [parser, *sub.choices.values()]:  # no prefix matching: `--res 64` must not mean `--resume` and a stray 64
        p.allow_abbrev = False
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread where Ctrl-C would raise KeyboardInterrupt: the same
    clean ending (temporary files removed by the ``finally`` blocks on the way, the resume hint)."""


def _on_sigterm(signum, frame):  # noqa: ARG001 (signal handler signature)
    raise Terminated()


def _one_line_warning(command: str):
    """A ``warnings.showwarning`` printing ``prt <command>: warning: <message>`` on one line, without
    the file, line number and source line Python's format adds (they name the library's code, not
    anything the user typed)."""
    def show(message, category, filename, lineno, file=None, line=None):  # noqa: ARG001
        text = " ".join(str(message).split())
        print(f"prt {command}: warning: {text}", file=file or sys.stderr)
    return show


def _stdout_reader_left() -> bool:
    """Whether standard output is a pipe whose reader has closed it (``prt ... | head``): its write
    end polls as an error. A BrokenPipeError from any other pipe must not silence standard output."""
    import select

    try:
        fd = sys.stdout.fileno()
        p = select.poll()
        p.register(fd, select.POLLOUT)
        return any(ev & select.POLLERR for _, ev in p.poll(0))
    except (OSError, ValueError, AttributeError):  # no poll (Windows) or no real stdout: assume the usual case
        return True


def _in_cli_words(parser: argparse.ArgumentParser, command: str, message: str, names: dict[str, str] | None = None) -> str:
    """An error message in the words the user typed: a library parameter written ``name=value``
    (``quad_bands=0``, ``view_deg=nan``, ``up='q'``) whose name is an option of this subcommand
    (``--quad-bands``) is named by that option, and a Python ``None`` in "accepted" as "unset".
    ``prt bench`` messages keep their config keys (what its user types)."""
    import re

    if command == "bench":
        return message
    sub = parser._subparsers._group_actions[0].choices.get(command) if parser._subparsers else None  # type: ignore[union-attr]
    pairs = dict(names or {})  # library name -> option (a command's own, e.g. precompute's kind parameters)
    for a in getattr(sub, "_actions", []):
        if not a.option_strings or a.dest in ("help", "debug"):
            continue
        flag = max(a.option_strings, key=len)
        for name in (a.dest, flag.lstrip("-").replace("-", "_")):
            pairs.setdefault(name, flag)
    for name, flag in pairs.items():
        if re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", message):  # the message names the option already
            continue  # ("pass overwrite=True (CLI: --overwrite)")
        message = re.sub(rf"(?<![\w'\"./:-]){re.escape(name)}= ?", f"{flag} ", message)
    return re.sub(r"(accepted: [^;]*?) or None\b", r"\1 or unset", message)


def parse_args(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> argparse.Namespace:
    """``argv`` (the words after ``prt``; None: ``sys.argv[1:]``) parsed as ``prt`` parses it, without running
    anything: ``key=value`` overrides after an option still count as overrides (``prt bench CONFIG --dry-run
    key=value``); anything else left over ends as argparse's usage error (``SystemExit(2)``, one line on stderr).
    tests/test_docs_commands.py parses every documented command line with it."""
    args, extra = parser.parse_known_args(argv)
    if extra:  # options between the positionals: `prt bench CONFIG --dry-run key=value`
        if any(a.startswith("-") for a in extra) or not hasattr(args, "overrides"):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = [*(args.overrides or []), *extra]
    return args


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parse_args(parser, argv)
    if getattr(args, "func", None) is None:
        if args.command is None and "bench" in parser._subparsers._group_actions[0].choices:  # type: ignore[union-attr]
            # `prt` alone behaves as `prt bench` (the default benchmark).
            return main(["bench", *(argv or [])])
        parser.print_help()
        return 2
    main_thread = threading.current_thread() is threading.main_thread()
    old_term = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning(args.command)
            return int(args.func(args) or 0)
    except BrokenPipeError:
        if not _stdout_reader_left():  # another pipe broke (a worker's, a child's): an error, not `| head`
            if getattr(args, "debug", False):
                raise
            print(f"prt {args.command}: error: a pipe to another process broke (BrokenPipeError)", file=sys.stderr)
            return 2
        import os  # `prt ... | head`: the reader left; not an error

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt as e:
        if getattr(args, "debug", False):
            raise
        hint = getattr(args, "resume_hint", None)
        how = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        print(f"prt {args.command}: {how}" + (f"; {hint}" if hint else ""), file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    except (ValueError, FileNotFoundError, FileExistsError, TypeError, OSError) as e:
        if getattr(args, "debug", False):
            raise
        hint = getattr(args, "resume_hint", None) if isinstance(e, ChildProcessError) else None  # a worker died mid-run
        if isinstance(e, OSError) and e.strerror and e.filename is not None and "Errno" in str(e):  # not "[Errno 20] ..."
            e = OSError(f"{str(e.filename)!r}: {e.strerror}"
                        + (f" (and {str(e.filename2)!r})" if e.filename2 is not None else ""))
        text = _in_cli_words(parser, args.command, " ".join(str(e).split()), getattr(args, "cli_names", None))  # one line
        print(f"prt {args.command}: error: {text}" + (f"; {hint}" if hint else ""), file=sys.stderr)
        return 2
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, old_term if old_term is not None else signal.SIG_DFL)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
