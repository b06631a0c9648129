"""Errors that stages raise for users."""


class InputError(ValueError):
    """A problem with the user's input, reported as one clear line without a traceback."""
