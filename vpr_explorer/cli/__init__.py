"""The ``vpr-explorer`` command line: one module per command, which the parser lists.

Commands (``vpr-explorer COMMAND --help`` for each one's options):

    evaluate   run a protocol on a dataset and print the paper's kind of table  (evaluate.py)
    acceptance every acceptance rule on one dataset's queries: the authors' table (acceptance.py)
    failures   one PNG per failing query with its answers and true match, an index  (failures.py)
    record     play a query traversal back against a database into a rerun .rrd  (record.py)
    list       the dataset's images in descriptor order                          (listing.py)
    sweep      one protocol over a grid of group × step: tables, CSV, JSON       (sweep.py)
    bench      every dataset × descriptor × protocol: table, CSV, JSON, HTML      (bench.py)
    extract    fill the descriptor cache, with local threads or on Ray           (extract.py)
    datasets   the public datasets the explorer knows: home, licence, URLs       (datasets.py)
    fetch      download one into $VPR_EXPLORER_DATA: resumed, checked, unpacked (fetch.py)
    app        serve the packaged explorer with Streamlit                        (vpr_explorer.app.launch)

Each command's module has ``add_arguments(parser)`` and ``run(args) -> int``; ``common.py``
holds what several share (the dataset options, progress bars, the protocol options'
checks); ``parser.py`` lists the commands (``build_parser``) and runs one
(``run_command``: bad input is one ``error:`` line and exit 2, Ctrl-C one ``error:
interrupted`` line and exit 130). ``python -m vpr_explorer.cli`` runs :func:`main`, as the
console script does.

This module imports only the standard library, so that the console script starts at once
and handles a Ctrl-C while the commands' modules (numpy, scipy and more: a second or
longer) are imported. Python's own handler would turn one into a traceback (or, raised
inside a library's import, into another error, or into nothing when that import swallows
it); :func:`main` instead prints :data:`STARTING` and exits 130 at once. What it cannot
reach is Python's own start-up before the script calls :func:`main` (some tens of
milliseconds: the interpreter, ``site`` and the script's import of this package): a
Ctrl-C then ends the process as Python does, by the signal or with Python's traceback.
"""

from __future__ import annotations

import os
import signal

__all__ = ["STARTING", "main"]

#: the line a Ctrl-C prints while the command's modules are still loading
STARTING = "error: interrupted while starting; nothing was done"


def main(argv: list[str] | None = None) -> int:
    """Run ``vpr-explorer`` with the arguments ``argv`` (default ``sys.argv[1:]``).

    While the commands' modules are imported, a Ctrl-C prints :data:`STARTING` and exits
    130; from then on ``parser.run_command`` handles it (``error: interrupted``, 130).

    Returns:
        The command's exit status: 0, 2 after bad input, 130 after Ctrl-C.
    """
    guarded = _end_at_once_while_starting()
    try:
        from vpr_explorer.cli.parser import run_command
    finally:
        if guarded:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    return run_command(argv)


def _end_at_once_while_starting() -> bool:
    """Install :func:`_end_at_once` for SIGINT where Python's own handler has it; whether it was installed.

    Not where SIGINT is ignored (``nohup``, a background job) or taken by another handler,
    nor outside the main thread, where no handler can be set.
    """
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return False
    try:
        signal.signal(signal.SIGINT, _end_at_once)
    except ValueError:  # not the main thread
        return False
    return True


def _end_at_once(signum: int, frame) -> None:
    """SIGINT while importing: one line and exit 130 here, whatever module is half-imported."""
    # os.write to fd 2 and os._exit: no Python-level buffer or cleanup that a half-run import could hold or break
    try:
        os.write(2, (STARTING + "\n").encode())
    except OSError:  # no stderr to write to
        pass
    os._exit(130)
