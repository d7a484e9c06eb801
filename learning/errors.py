"""The one exception type for bad input from a user."""


class InputError(ValueError):
    """Bad input (file, shape, name, value); its message is one line that names
    the problem. Command-line programs print it and exit non-zero."""
