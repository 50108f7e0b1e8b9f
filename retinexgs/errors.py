"""Error types shared by every stage."""


class UserError(Exception):
    """A problem with the user's input (a path, a file, a flag) that the CLI reports without a traceback.

    The message names the offending file or argument and says what to do about it.
    """


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill PID``, ``timeout``) received: raised in the main thread by the CLI's handler. A kind of
    KeyboardInterrupt, so every clean-up made for Ctrl-C runs for it too; the CLI exits with 143."""
