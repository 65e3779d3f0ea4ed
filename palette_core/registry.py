"""Name-to-function tables for the steps that have several methods (palette, weights).

A method is a function whose first parameters are the step's inputs and whose
keyword-only parameters are its options, each with a default; ``call_method``
checks the name and that every option given belongs to the chosen method
(colour-science's ``validate_method`` and ``filter_kwargs``, made strict).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

from .errors import InputError


def validate_method(name: str, methods: dict[str, Callable], what: str) -> Callable:
    """The function registered as ``name``; InputError listing the valid names otherwise."""
    if name not in methods:
        raise InputError(f"{what} must be one of {', '.join(sorted(methods))}, got {name!r}")
    return methods[name]


def method_options(function: Callable) -> dict[str, inspect.Parameter]:
    """The keyword-only parameters (the options) of a method, by name."""
    return {name: p for name, p in inspect.signature(function).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY}


def check_options(methods: dict[str, Callable], name: str, what: str, options: dict) -> Callable:
    """The method ``name``, after checking that every option given is one of its own.

    Raises
    ------
    InputError
        If the name is unknown or an option belongs to another method (or to none).
    """
    function = validate_method(name, methods, what)
    accepted = method_options(function)
    for option in options:
        if option not in accepted:
            owners = [m for m, f in methods.items() if option in method_options(f)]
            where = f"{what} {' or '.join(owners)} only" if owners else f"no {what}"
            raise InputError(f"option {option} applies to {where}, not {name}")
    return function


def spatial(function: Callable) -> Callable:
    """Mark a weight method that takes whole images, not distinct colours (``weights``)."""
    function.spatial = True
    return function


def is_spatial(function: Callable) -> bool:
    return getattr(function, "spatial", False)


def call_method(methods: dict[str, Callable], name: str, what: str, *inputs, **options):
    """Call method ``name`` of ``methods`` on ``inputs`` with its ``options`` (checked first)."""
    return check_options(methods, name, what, options)(*inputs, **options)
