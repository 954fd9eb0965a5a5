"""The ``bpp`` program's entry point, light enough to take Ctrl-C and SIGTERM from its first moment.

The command line imports every benchmark (and a command that builds a model, torch, when it runs), which takes up to
seconds; a signal during those seconds would otherwise end the program with an import's traceback (Ctrl-C) or without
a word (SIGTERM). Here both end it as they do later: one line and the status 128 + the signal's number.
"""

from __future__ import annotations

import signal
import sys

from bpp.errors import raise_interrupted


def main() -> None:
    """Run ``bpp`` with the process's arguments; a signal while the command line loads ends it in one line."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # one started ignoring a signal keeps ignoring it
        signal.signal(signal.SIGINT, raise_interrupted)
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, raise_interrupted)
    try:
        # here, not at the top: the command line loads with the handlers above already in place
        from bpp.cli import main as run

        run()  # takes the handlers over, and reports a signal itself from here on
    except KeyboardInterrupt as err:
        signum = getattr(err, "signum", signal.SIGINT)
        print(f"bpp: interrupted by {signal.Signals(signum).name}", file=sys.stderr)
        sys.exit(128 + signum)
