"""What ``terrain-prior`` and ``terrain-track`` share: ``-q`` anywhere, negative option values, one-line
warnings and errors, and the exit codes (0 done, 1 an ``error:`` line, 2 an argparse usage error)."""

from __future__ import annotations

import argparse
import logging
import math
import re
import sys
import warnings
from collections.abc import Callable

EXIT_OK = 0
"""Exit code: done."""
EXIT_ERROR = 1
"""Exit code: an ``error:`` line (bad input, an output that cannot or must not be written)."""
EXIT_USAGE = 2
"""Exit code: a usage error (argparse: unknown option, missing or malformed argument)."""

_NEGATIVE_VALUE = re.compile(r"^-(\.?\d[\w.:,+-]*|inf(inity)?|nan)$", re.IGNORECASE)
"""A value that starts with '-' but is no option: -1e-3, -inf, -nan, a τ range "-3:3:0.25" or list "-1,1"."""


def quiet_parent() -> argparse.ArgumentParser:
    """A parent parser with ``-q/--quiet`` for every subcommand, so ``-q`` works before and after it.
    Its default is suppressed so the subcommand's absent ``-q`` leaves the top level's value alone."""
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="no progress bars")
    return parent


def attach_negative_values(argv: list[str]) -> list[str]:
    """``--opt -inf`` as ``--opt=-inf``, the form argparse documents for values that start with '-'
    (it takes a separate one for an option unless it is a plain negative integer or decimal)."""
    out: list[str] = []
    for token in argv:
        prev = out[-1] if out else ""
        if _NEGATIVE_VALUE.match(token) and prev.startswith("--") and "=" not in prev:
            out[-1] = f"{prev}={token}"
        else:
            out.append(token)
    return out


def number(minimum: float | None = None, maximum: float | None = None, *, strict: bool = True) -> Callable[[str], float]:
    """The argparse type of a finite float option in (``minimum``, ``maximum``) (``strict``) or in the closed range,
    a bound of None being open: a bad value is a usage error that names the option (``argument --tau: ...``)."""
    below, above = (">", "<") if strict else (">=", "<=")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        low = minimum is not None and not (value > minimum if strict else value >= minimum)
        high = maximum is not None and not (value < maximum if strict else value <= maximum)
        if not math.isfinite(value) or low or high:
            rule = " and ".join(f"{op} {bound:g}" for op, bound in ((below, minimum), (above, maximum)) if bound is not None)
            raise argparse.ArgumentTypeError(f"must be a finite number{' ' + rule if rule else ''}, got {text!r}")
        return value

    return parse


def count(minimum: int) -> Callable[[str], int]:
    """The argparse type of an integer option >= ``minimum``: a bad value is a usage error naming the option."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {text!r}")
        return value

    return parse


_OWN_LOGGERS = ("pipeline", "tracker", "common")
"""Packages whose INFO messages a command prints; other libraries' only from WARNING up."""


def _shown(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.WARNING or record.name.split(".", 1)[0] in _OWN_LOGGERS


class _Prefixed(logging.Formatter):
    """``prog: message``, with ``warning:`` / ``error:`` before the message of those levels."""

    def __init__(self, prog: str) -> None:
        super().__init__()
        self.prog = prog

    def format(self, record: logging.LogRecord) -> str:
        level = f"{record.levelname.lower()}: " if record.levelno >= logging.WARNING else ""
        return f"{self.prog}: {level}{record.getMessage()}"


def _error_message(exc: Exception) -> str:
    """The ``error:`` text of an exception: a ValueError's message names what is wrong; an OSError
    is given as ``file: reason``."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def run_cli(prog: str, parser: argparse.ArgumentParser, argv: list[str] | None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``), run the chosen subcommand's ``func(args)``, and turn
    every input or output problem into one ``prog: error: ...`` line with exit code 1. Warnings print as
    ``prog: warning: message`` (no source line)."""
    args = parser.parse_args(attach_negative_values(sys.argv[1:] if argv is None else list(argv)))
    args.quiet = getattr(args, "quiet", False)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Prefixed(prog))
    handler.addFilter(_shown)
    root = logging.getLogger()
    old_level = root.level
    root.addHandler(handler)
    root.setLevel(logging.INFO)

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        print(f"{prog}: warning: {message}", file=sys.stderr)

    func: Callable[[argparse.Namespace], None] = args.func
    try:
        with warnings.catch_warnings():
            warnings.showwarning = show
            func(args)
    except (ValueError, OSError) as exc:  # every input problem names the file, table, key or argument
        print(f"{prog}: error: {_error_message(exc)}", file=sys.stderr)
        return EXIT_ERROR
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
    return EXIT_OK
