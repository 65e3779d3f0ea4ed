"""Shared command-line plumbing: one-line errors and exit code 2, flags generated from
method options and config dataclasses."""

from __future__ import annotations

import argparse
import ast
import contextvars
import dataclasses
import enum
import inspect
import os
import re
import signal
import sys
import textwrap
import threading
import typing
import warnings
from collections.abc import Callable
from typing import NoReturn

from ..errors import InputError, cli_line
from ..registry import method_options


class ArgumentParser(argparse.ArgumentParser):
    """argparse that raises ``InputError`` instead of printing usage and exiting, and that
    tells ``run_cli`` the flags of the (sub)command parsed, so that an error's hints name
    only those."""

    def error(self, message: str):
        raise InputError(message)

    def parse_known_args(self, args=None, namespace=None):
        _FLAGS.set(frozenset(self._option_string_actions))  # a subcommand's come last
        return super().parse_known_args(args, namespace)


class Terminated(BaseException):
    """SIGTERM or SIGHUP arrived: unwinds like KeyboardInterrupt, so outputs clean up."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


#: The signals that end a command; the first unwinds it, any later one is ignored, so that
#: the clean-up it started is never interrupted.
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _terminate(signum, frame):
    for sig in SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    raise KeyboardInterrupt if signum == signal.SIGINT else Terminated(signum)


def run_cli(prog: str, body: Callable[[], int]) -> int:
    """Run a CLI body; bad input and failed reads or writes (a full disk, say) become one
    line on stderr and exit code 2, naming only flags that the command has
    (``ArgumentParser``), with no library warning before it: warnings raised while the body
    runs are shown when it returns or by ``show_warnings``. SIGINT, SIGTERM and SIGHUP
    unwind the body, so that staged outputs are removed, and exit with 128 + the signal's
    number, whenever they arrive."""
    previous = {}
    try:
        if threading.current_thread() is threading.main_thread():
            previous = {sig: signal.signal(sig, _terminate) for sig in SIGNALS}
        with warnings.catch_warnings(record=True) as caught:
            _WARNINGS.append(caught)
            try:
                code = _reported(prog, body)
            finally:
                _WARNINGS.remove(caught)
        if code != 2:
            _show(caught)
        return code
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT
    except Terminated as exc:
        print(f"{prog}: stopped by {signal.Signals(exc.signum).name}", file=sys.stderr)
        return 128 + exc.signum
    finally:
        if all(signal.getsignal(sig) is not signal.SIG_IGN for sig in previous):
            for sig, handler in previous.items():  # no signal came: as it was
                signal.signal(sig, handler)


def _reported(prog: str, body: Callable[[], int]) -> int:
    """``body()``, with bad input and failed reads or writes said in one line (exit code 2)."""
    flags = _FLAGS.set(frozenset())
    try:
        return body()
    except InputError as exc:
        print(f"{prog}: error: {one_line(cli_line(exc, _FLAGS.get() or None))}",
              file=sys.stderr)
        return 2
    except OSError as exc:
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"{prog}: error: {one_line(f'{exc.strerror or exc}{where}')}", file=sys.stderr)
        return 2
    finally:
        _FLAGS.reset(flags)


#: Longest error message shown, in characters: a value from a hostile file is cut.
MAX_MESSAGE = 1000
#: The flags of the (sub)command being parsed (``ArgumentParser.parse_known_args``).
_FLAGS: contextvars.ContextVar[frozenset] = contextvars.ContextVar("flags", default=frozenset())
#: The warnings held back by the commands running (``run_cli``), innermost last.
_WARNINGS: list[list] = []


def one_line(text: str) -> str:
    """``text`` on one line of at most ``MAX_MESSAGE`` characters (a numpy array's repr or a
    file's value folded and cut)."""
    text = " ".join(text.split())
    return text if len(text) <= MAX_MESSAGE else text[:MAX_MESSAGE - 3] + "..."


def show_warnings() -> None:
    """Show the warnings the running command has held back so far (``run_cli``): for a
    command that goes on once it has started well (the studio)."""
    if _WARNINGS:
        _show(_WARNINGS[-1])


def _show(caught: list) -> None:
    """Raise the held-back warnings again, through the filters in force outside."""
    held = list(caught)
    caught.clear()
    for message in held:
        warnings.warn_explicit(message.message, message.category, message.filename,
                               message.lineno, source=message.source)


def exit_without_teardown(code: int) -> NoReturn:
    """End a finished command's process with ``code``, skipping Python's teardown of its
    modules: after numba has run, freeing them is a noticeable share of a one-photo
    ``palette-decompose`` (docs/decisions/0001-refined-palette.md). Every output is
    closed and in place by then (``outputs.py``); the standard streams are flushed here."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can reach it
            pass
    os._exit(code)


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


def add_config_arguments(parser: argparse.ArgumentParser, defaults, prefix: str = "") -> None:
    """One flag per field of the dataclass instance ``defaults``, nested dataclasses prefixed by
    their field name (``TrainConfig.grid.voxels`` -> ``--grid-voxels``), typed by the
    annotations, documented by the field docstrings, defaulting to ``defaults``' values.
    Enums give choices; tuples take one value per element; booleans give ``--x`` and
    ``--no-x``; ``X | None`` fields also take ``none``.
    """
    cls = type(defaults)
    hints = typing.get_type_hints(cls)
    docs = _field_docstrings(cls)
    for f in dataclasses.fields(cls):
        kind, name = hints[f.name], prefix + f.name
        default = getattr(defaults, f.name)
        if dataclasses.is_dataclass(kind):
            add_config_arguments(parser, default, name + "_")
            continue
        default = str(default) if isinstance(default, enum.Enum) else default
        options = {"dest": name, "default": default,
                   "help": f"{docs.get(f.name, '').replace('``', '')} (default {_shown(default)})"}
        if typing.get_origin(kind) is tuple:
            options |= {"type": typing.get_args(kind)[0], "nargs": len(typing.get_args(kind))}
        elif isinstance(kind, type) and issubclass(kind, enum.Enum):
            options |= {"type": str, "choices": [str(member) for member in kind]}
        elif kind is bool:
            options["action"] = argparse.BooleanOptionalAction
        elif type(None) in typing.get_args(kind):  # X | None
            options |= {"type": _or_none(next(t for t in typing.get_args(kind)
                                             if t is not type(None))),
                        "metavar": "X|none"}
        else:
            options["type"] = kind
        parser.add_argument("--" + name.replace("_", "-"), **options)


def config_from_args(cls: type, args: argparse.Namespace, prefix: str = ""):
    """The dataclass ``cls`` built from the flags of ``add_config_arguments``."""
    values, hints = {}, typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        kind = hints[f.name]
        values[f.name] = (config_from_args(kind, args, prefix + f.name + "_")
                          if dataclasses.is_dataclass(kind) else getattr(args, prefix + f.name))
    return cls(**values)


def _or_none(parse):
    """An argparse type: ``none`` -> None, anything else through ``parse``."""

    def parse_or_none(text: str):
        return None if text.lower() == "none" else parse(text)

    parse_or_none.__name__ = parse.__name__  # argparse names the type in its errors
    return parse_or_none


def _field_docstrings(cls: type) -> dict[str, str]:
    """The string literal under each field of a dataclass's source, on one line."""
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    docs = {}
    for field, doc in zip(body, body[1:]):
        if (isinstance(field, ast.AnnAssign) and isinstance(doc, ast.Expr)
                and isinstance(doc.value, ast.Constant) and isinstance(doc.value.value, str)):
            docs[field.target.id] = " ".join(doc.value.value.split())
    return docs


def _shown(default) -> str:
    if isinstance(default, tuple):
        return " ".join(map(str, default))
    return str(default)
