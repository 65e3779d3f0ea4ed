"""Shared command-line plumbing: one-line errors, exit code 2, flags for method options."""

from __future__ import annotations

import argparse
import inspect
import re
import sys
import typing
from collections.abc import Callable

from ..errors import InputError
from ..registry import method_options


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


def add_method_options(parser: argparse.ArgumentParser, methods: dict[str, Callable]) -> None:
    """One flag per keyword option of the registered ``methods`` (``spatial_scale`` ->
    ``--spatial-scale``), typed by its annotation and documented by its docstring.

    The flags default to None, so that only options the user gives reach the method.
    """
    seen: dict[str, list[str]] = {}
    for name, function in methods.items():
        for option in method_options(function):
            seen.setdefault(option, []).append(name)
    for option, owners in seen.items():
        function = methods[owners[0]]
        parameter = method_options(function)[option]
        kind = typing.get_type_hints(function)[option]
        parser.add_argument("--" + option.replace("_", "-"), type=kind, default=None,
                            metavar=option.split("_")[-1][0].upper(),
                            help=f"{'/'.join(owners)} only: {_docstring_entry(function, option)} "
                                 f"(default {parameter.default})")


def given_options(args: argparse.Namespace, methods: dict[str, Callable]) -> dict:
    """The method options set on the command line, by parameter name."""
    names = {option for function in methods.values() for option in method_options(function)}
    return {name: getattr(args, name) for name in sorted(names) if getattr(args, name) is not None}


def _docstring_entry(function: Callable, name: str) -> str:
    """The text under ``name : type`` in a numpydoc Parameters section, on one line."""
    doc = inspect.getdoc(function) or ""
    match = re.search(rf"^{name} :.*\n((?:    .*\n?)+)", doc, re.MULTILINE)
    return " ".join(match.group(1).split()) if match else name
