"""The exception types for bad input, mapped to exit code 2 by every CLI.

The library words its errors without the command line: an error may name the setting it
is about (``argument``) and the settings that would accept the input (``fixes``), and each
front end says them its own way: a command line as flags (``cli_line``), the studio as
its buttons.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence


class InputError(ValueError):
    """Bad input from the user: a missing file, a wrong shape, an invalid option.

    Parameters
    ----------
    message : str
    argument : str, optional
        The setting the message is about (a keyword argument's name: ``"workers"``).
    fixes : sequence of (str, str)
        Settings that would accept the input and what each does:
        ``[("force", "to overwrite")]``.
    """

    def __init__(self, message: str, argument: str | None = None,
                 fixes: Sequence[tuple[str, str]] = ()):
        super().__init__(message)
        self.argument, self.fixes = argument, tuple(fixes)


class OutputExists(InputError):
    """An output is already there and ``force`` was not given (an editor asks to confirm);
    ``force`` would do ``what`` ("to overwrite")."""

    def __init__(self, message: str, what: str = "to overwrite"):
        super().__init__(message, fixes=[("force", what)])


def flag(name: str) -> str:
    """The command-line flag of the setting ``name``: ``max_pixels`` -> ``--max-pixels``."""
    return "--" + name.replace("_", "-")


def cli_line(exc: InputError, flags: Collection[str] | None = None) -> str:
    """``exc`` as a command line says it: its setting and its fixes as flags (only those
    among ``flags``, the command's, when given)."""
    text = str(exc)
    if getattr(exc, "argument", None):
        text = f"{flag(exc.argument)}: {text}"
    fixes = [(name, what) for name, what in getattr(exc, "fixes", ())
             if flags is None or flag(name) in flags]
    if fixes:
        text += " (use " + " or ".join(f"{flag(name)} {what}" for name, what in fixes) + ")"
    return text


def first_line(exc: BaseException) -> str:
    """The first line of what ``exc`` says, or its type's name when it says nothing: a
    library's exception shown as one line of ours."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
