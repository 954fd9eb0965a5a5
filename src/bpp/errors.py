"""The one exception type for errors a user can cause: a bad flag, file, store, checkpoint or prompt.

The command line prints a :class:`UserError` as one line naming the command; any other exception is a bug and keeps
its traceback. It subclasses ValueError so that library callers catching ValueError keep working.

A command stopped by Ctrl-C (SIGINT) or SIGTERM ends with one line and the status 128 + the signal's number (130,
143), after every writer has removed what it left half-written: the command line turns both signals into
:class:`Interrupted`, a KeyboardInterrupt, so that SIGTERM runs the same clean-up as Ctrl-C.
"""

import importlib
import os
import signal
import sys
import threading
import time


class UserError(ValueError):
    """An input the user gave (flag, file, store, checkpoint, prompt) is wrong; the message names it and what was
    expected."""


class Interrupted(KeyboardInterrupt):
    """The process was asked to stop by signal `signum` (SIGINT or SIGTERM): a KeyboardInterrupt, so that whatever
    cleans up after Ctrl-C cleans up after either."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def raise_interrupted(signum: int, frame) -> None:
    """The signal handler that turns SIGINT and SIGTERM into :class:`Interrupted`. The program is stopping: a
    library's background thread that fails on the way down (torch's file-descriptor sharing, when a loader process it
    talks to is stopped) must not print a traceback after the one-line message."""
    threading.excepthook = lambda args: None
    sys.unraisablehook = _send_again
    raise Interrupted(signum)


def _send_again(unraisable) -> None:
    """Python ignores an exception raised inside some callbacks (the import machinery's weakref callbacks, a
    ``__del__``): an :class:`Interrupted` raised there would be lost and the command would go on. Send its signal
    again, a moment later and from another thread, so that it is raised at the main thread's next ordinary line (once
    more if that is another such callback); report any other exception as Python does."""
    if isinstance(unraisable.exc_value, Interrupted):
        try:
            threading.Thread(target=_send_later, args=(unraisable.exc_value.signum,), daemon=True).start()
            return
        except RuntimeError:  # the interpreter is already shutting down: nothing is left to stop
            pass
    sys.__unraisablehook__(unraisable)


def _send_later(signum: int) -> None:
    """Send `signum` to this process once the hook that started this thread has returned."""
    time.sleep(0.05)
    os.kill(os.getpid(), signum)


def require_extra(module: str, extra: str):
    """Import `module`, which only optional extra `extra` installs; a missing one is a UserError saying what to
    install (``pip install -e '.[extra]'`` in bpp's clone) rather than an ImportError from deep inside a command."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name is None or module.split(".")[0] != err.name.split(".")[0]:
            raise  # the module is there but one of its own imports failed: a broken install, not a missing extra
        raise UserError(
            f"this needs the {extra!r} extra, which is not installed: pip install -e '.[{extra}]' in bpp's clone"
        ) from err
