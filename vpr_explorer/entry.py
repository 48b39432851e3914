"""The ``vpr-explorer`` console script: a Ctrl-C while the command starts ends it with one line.

The command line's modules import numpy, scipy and more, which takes a second or longer;
Python's own handler would turn a Ctrl-C meanwhile into a traceback (or, raised inside a
library's import, into another error, or into nothing when that import swallows it). This
module imports only the standard library: :func:`main` installs a handler that prints one
``error:`` line and exits 130 at once, imports :mod:`vpr_explorer.cli`, gives Ctrl-C back
to Python and runs :func:`vpr_explorer.cli.main`, which handles it from then on
(``error: interrupted``, 130). ``python -m vpr_explorer.cli`` comes here too.

What it cannot reach is Python's own start-up before the script calls :func:`main` (some
tens of milliseconds: the interpreter, ``site`` and the script's imports of this module):
a Ctrl-C then ends the process as Python does, by the signal or with Python's traceback.
"""

from __future__ import annotations

import os
import signal

#: the line a Ctrl-C prints while the command's modules are still loading
STARTING = "error: interrupted while starting; nothing was done"


def _end_at_once(signum: int, frame) -> None:
    """SIGINT while importing: one line and exit 130 here, whatever module is half-imported."""
    # os.write to fd 2 and os._exit: no Python-level buffer or cleanup that a half-run import could hold or break
    try:
        os.write(2, (STARTING + "\n").encode())
    except OSError:  # no stderr to write to
        pass
    os._exit(130)


def main() -> int:
    """Run ``vpr-explorer`` with Ctrl-C handled from this call on; the command's exit status."""
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.default_int_handler:  # not where SIGINT is ignored (nohup, a background job) or taken
        signal.signal(signal.SIGINT, _end_at_once)
    from vpr_explorer import cli

    if previous is signal.default_int_handler:
        signal.signal(signal.SIGINT, previous)
    return cli.main()
