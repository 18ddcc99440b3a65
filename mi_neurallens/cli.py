"""The ``mi-neurallens`` command.  Each sub-command lives in ``mi_neurallens/commands/<name>.py``,
which defines ``add_parser(subparsers)``; commands are imported lazily so ``--help`` is fast."""
from __future__ import annotations

import argparse
import importlib
import sys

#: sub-command name -> module in mi_neurallens.commands
COMMANDS = {
    "demo": "demo",
    "lens": "lens",
    "render": "render",
    "compare": "compare",
    "train": "train", "evaluate": "evaluate", "merge": "merge",
    "accuracy": "accuracy",
    "flare": "flare",
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mi-neurallens",
                                description="Real camera lenses for Mitsuba 3: exact and neural lens transport.")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, mod in COMMANDS.items():
        try:
            m = importlib.import_module(f"mi_neurallens.commands.{mod}")
        except ImportError as e:  # a command whose module is not there yet
            if f"mi_neurallens.commands.{mod}" in str(e):
                continue
            raise
        m.add_parser(sub)
    return p


def _version():
    from . import __version__
    return __version__


def main(argv=None) -> int:
    from .errors import NeuralLensError
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)     # the command line, as typed (train records it)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except NeuralLensError as e:
        print(f"mi-neurallens: error: {e}", file=sys.stderr)
        return 1
    except FileNotFoundError as e:
        print(f"mi-neurallens: error: {e}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `mi-neurallens lens info X | head`
        import os
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
