"""The one exception type for errors a user can cause: a bad flag, file, store, checkpoint or prompt.

The command line prints a :class:`UserError` as one line naming the command; any other exception is a bug and keeps
its traceback. It subclasses ValueError so that library callers catching ValueError keep working.
"""


class UserError(ValueError):
    """An input the user gave (flag, file, store, checkpoint, prompt) is wrong; the message names it and what was
    expected."""
