"""The one exception type for bad input, mapped to exit code 2 by every CLI."""


class InputError(ValueError):
    """Bad input from the user: a missing file, a wrong shape, an invalid option."""
