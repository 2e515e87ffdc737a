"""The one error type that means "the user's input is wrong"."""


class UserError(Exception):
    """An error caused by the user's input: the CLI prints its message without a traceback."""
