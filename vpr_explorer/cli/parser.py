"""The ``vpr-explorer`` parser, which lists the commands, and :func:`run_command`, which runs one.

Bad input prints one ``error:`` line naming the file or parameter and exits 2; Ctrl-C
prints one ``error: interrupted`` line and exits 130. Either way the progress bars are
cleared first, so that the line stands on its own.
"""

from __future__ import annotations

import argparse
import sys

import vpr_explorer
from vpr_explorer.app import launch
from vpr_explorer.cli import acceptance, bench, datasets, evaluate, extract, failures, fetch, listing, record, sweep
from vpr_explorer.cli.common import BARS, HelpFormatter
from vpr_explorer.descriptors import ExtractionInterrupted
from vpr_explorer.errors import VPRInputError

#: the commands: name, module (``add_arguments(parser)``, ``run(args) -> int``), one line of help
COMMANDS = (
    ("evaluate", evaluate, "run a protocol and print the paper's kind of table"),
    ("acceptance", acceptance, "every acceptance rule on one query traversal against one database: the "
                               "authors' table of F1, rejection and AUC-PR"),
    ("failures", failures, "draw every query one method fails: a PNG of its candidates each, an index.html and "
                           "a CSV"),
    ("record", record, "play a query traversal back against a database: write a rerun .rrd"),
    ("list", listing, "print the dataset's images in descriptor order (the rows of a .npy to bring)"),
    ("sweep", sweep, "run a protocol over a grid of group × step (both readings): tables, CSV, JSON"),
    ("bench", bench, "every dataset × descriptor × protocol in one run: one table, CSV, JSON and an HTML report"),
    ("extract", extract, "fill the descriptor cache for a dataset: local threads, or a Ray cluster with "
                         "--ray ADDRESS|local"),
    ("datasets", datasets, "the public datasets the explorer knows: home, licence, size, layout, URLs and sha256"),
    ("fetch", fetch, "download a public dataset into $VPR_EXPLORER_DATA (resumable, checked, unpacked safely)"),
    ("app", launch, "open the explorer: Streamlit on the packaged app, from any directory"),
)
#: the line a Ctrl-C prints once the command runs
INTERRUPTED = "interrupted; run the same command again to resume (descriptors computed so far are cached)"


def build_parser() -> argparse.ArgumentParser:
    """``vpr-explorer``'s parser: one sub-command per row of :data:`COMMANDS`, its ``run`` as ``func``."""
    parser = argparse.ArgumentParser(prog="vpr-explorer", description=vpr_explorer.__doc__.splitlines()[0],
                                     formatter_class=HelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    for name, module, help in COMMANDS:
        command = commands.add_parser(name, help=help, formatter_class=HelpFormatter)
        module.add_arguments(command)
        command.set_defaults(func=module.run)
    return parser


def run_command(argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) and run its command.

    Returns:
        The exit status: the command's (0), 2 after bad input (one ``error:`` line on
        stderr), 130 after Ctrl-C (one ``error: interrupted`` line).

    Raises:
        SystemExit: from argparse, for ``--help`` (0) and for options it refuses itself (2).
    """
    BARS.reset()
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except VPRInputError as exc:
        BARS.clear()
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        BARS.clear()
        # Ctrl-C during extraction: the finished batches are cached and the exception says how many.
        print(f"error: interrupted; {exc}" if isinstance(exc, ExtractionInterrupted) else f"error: {INTERRUPTED}",
              file=sys.stderr)
        return 130
