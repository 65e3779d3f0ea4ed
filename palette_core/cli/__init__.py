"""Shared command-line plumbing: one-line errors and exit code 2 on bad input."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from ..errors import InputError


class ArgumentParser(argparse.ArgumentParser):
    """argparse that raises ``InputError`` instead of printing usage and exiting."""

    def error(self, message: str):
        raise InputError(message)


def run_cli(prog: str, body: Callable[[], int]) -> int:
    """Run a CLI body; bad input becomes one line on stderr and exit code 2."""
    try:
        return body()
    except InputError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
