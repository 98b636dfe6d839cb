"""The ``ident`` command line (``../shared/spec/cli.md``).

One module per subcommand in this package, each with ``add_parser(sub)`` and
``run(args) -> int``.  Exit codes: 0 success, 2 bad input (an
:class:`~ident.errors.IdentError`, one line on stderr naming file, channel or
key), 1 internal failure, 3 a campaign that finished with failed recordings.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from ..errors import IdentError

__all__ = ["main", "COMMANDS"]

#: subcommand -> module in this package
COMMANDS: dict[str, str] = {
    "frequencies": "frequencies",
    "simulate": "simulate",
    "segment": "segment",
    "fit": "fit",
    "train": "train",
    "diagnose": "diagnose",
    "discrepancy": "discrepancy",
    "campaign": "campaign",
    "report": "report",
}


def _parser() -> tuple[argparse.ArgumentParser, dict]:
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="ident", description="Identification and wear diagnostics of rolling-mill drivelines.")
    parser.add_argument("--version", action="version", version=f"ident {__version__}",
                        help="print the version of ident and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    modules = {}
    for name, modname in COMMANDS.items():
        try:
            mod = importlib.import_module(f".{modname}", __name__)
        except ModuleNotFoundError as exc:  # a command whose stage is not built yet
            if exc.name and exc.name.endswith(f"cli.{modname}"):
                continue
            raise
        mod.add_parser(sub)
        modules[name] = mod
    return parser, modules


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    parser, modules = _parser()
    args = parser.parse_args(argv)

    def one_line(message, category, filename, lineno, file=None, line=None) -> None:
        print(f"ident {args.command}: warning: {message}", file=sys.stderr)

    try:
        with warnings.catch_warnings():  # warnings as one line each, not two
            warnings.simplefilter("default")
            warnings.showwarning = one_line
            code = modules[args.command].run(args)
    except IdentError as exc:
        print(f"ident {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"ident {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the contract maps anything else to 1
        import traceback
        traceback.print_exc()
        print(f"ident {args.command}: internal error: {type(exc).__name__}: {exc}",
              file=sys.stderr)
        return 1
    return int(code or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
