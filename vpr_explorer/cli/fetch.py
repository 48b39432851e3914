"""``vpr-explorer fetch NAME``: download a catalogue dataset into the data folder and print its ``--dataset`` path.

    vpr-explorer fetch gardens-point-walking                  # into $VPR_EXPLORER_DATA, else ~/vpr-data
    vpr-explorer fetch nordland-64x32 --to ~/vpr-data
    vpr-explorer fetch vpr-bench-corridor --from http://mirror.example/vpr/

Downloads into ``--to`` (default ``$VPR_EXPLORER_DATA``, else ``~/vpr-data``), resuming an
interrupted download from its ``.part`` file, checks the sha256 where the catalogue has one
(else prints the one it got, to pin with ``--sha256``), unpacks safely into a temporary
folder and renames it into place (``data.fetch`` says how). ``--from URL`` (or
``$VPR_EXPLORER_MIRROR``) fetches every file as ``URL/<file name>`` instead. A dataset
folder that exists already is skipped, not fetched again. Datasets served over rsync, by a
script or on request are refused by name with what to do.

Exit status: 0 when the dataset is there; 2 for a refusal or a failed download (one
``error:`` line naming the URL or file and what to do; no half-written dataset folder is
left, and a ``.part`` download is kept to resume).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from vpr_explorer.cli.common import bar
from vpr_explorer.data.catalogue import Access, find
from vpr_explorer.data.fetch import DEFAULT_DATA, MIRROR_ENV, TIMEOUT, data_folder, fetch, url_of
from vpr_explorer.settings import DATA_ENV


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``fetch``'s options: the dataset, the data folder, a mirror, a digest."""
    p.add_argument("name", metavar="NAME", help="a dataset of `vpr-explorer datasets`")
    p.add_argument("--to", type=Path, default=None, metavar="DIR",
                   help=f"the data folder that receives DIR/<dataset folder> (default: ${DATA_ENV}, else {DEFAULT_DATA})")
    p.add_argument("--from", dest="mirror", default=None, metavar="URL",
                   help=f"fetch every file as URL/<file name> (a mirror or a local copy; default: ${MIRROR_ENV}, else "
                        "the catalogue's addresses)")
    p.add_argument("--sha256", default=None, metavar="HEX",
                   help="the expected sha256 of the dataset's file that has no published one")
    p.add_argument("--timeout", type=float, default=TIMEOUT, metavar="S",
                   help="seconds without data before a download stops (run again to resume)")


def run(args: argparse.Namespace) -> int:
    """Fetch one dataset and print its ``--dataset`` path.

    Returns:
        0 (a refusal or a failed download raises ``VPRInputError``: exit 2).
    """
    dataset = find(args.name)
    mirror = args.mirror or os.environ.get(MIRROR_ENV, "").strip() or None
    to = args.to if args.to is not None else data_folder()
    if dataset.access is Access.DOWNLOAD:
        for d in dataset.downloads:
            print(f"{d.file_name}: {url_of(d, mirror)}")
    result = fetch(dataset, to, mirror=mirror, sha256=args.sha256, progress=_bars(), timeout=args.timeout)
    if result.skipped:
        print(f"{result.path} exists already: not fetched again (delete or rename it to fetch afresh)")
    for digest in result.digests:
        note = "checked" if digest.checked else "not published, so not verified: pin it with --sha256"
        print(f"sha256 {digest.sha256}  {digest.file_name} ({note})")
    print(f"{dataset.title} ({dataset.layout.value}): --dataset {result.path}")
    return 0


def _bars():
    """A ``fetch`` progress callback: one bar per file whose size the server gives, none for the others."""
    drawn: dict = {}

    def update(done: int, total: int, name: str) -> None:
        if total <= 0:
            return
        if name not in drawn:
            drawn.clear()
            drawn[name] = bar(name)
        drawn[name](min(done, total), total)

    return update
