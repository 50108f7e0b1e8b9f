"""Error types shared by every stage."""


class UserError(Exception):
    """A problem with the user's input (a path, a file, a flag) that the CLI reports without a traceback.

    The message names the offending file or argument and says what to do about it.
    """
