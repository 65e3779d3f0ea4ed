"""The exception types for bad input, mapped to exit code 2 by every CLI."""


class InputError(ValueError):
    """Bad input from the user: a missing file, a wrong shape, an invalid option."""


class OutputExists(InputError):
    """An output is already there and ``force`` was not given (an editor asks to confirm)."""
