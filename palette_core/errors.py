"""The exception types for bad input, mapped to exit code 2 by every CLI."""


class InputError(ValueError):
    """Bad input from the user: a missing file, a wrong shape, an invalid option."""


class OutputExists(InputError):
    """An output is already there and ``force`` was not given (an editor asks to confirm)."""


def first_line(exc: BaseException) -> str:
    """The first line of what ``exc`` says, or its type's name when it says nothing: a
    library's exception shown as one line of ours."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
