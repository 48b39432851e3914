"""``vpr-explorer datasets``: the public datasets the explorer knows (``data.catalogue``).

    vpr-explorer datasets                    # one line per dataset: name, access, layout, checksums, title
    vpr-explorer datasets nordland-64x32     # everything about one: home, licence, size, URLs, sha256, how

``vpr-explorer fetch NAME`` (``fetch.py``) downloads into ``--to`` (default ``$VPR_EXPLORER_DATA``, else ``~/vpr-data``),
resuming an interrupted download, checks the sha256 where the catalogue has one (else
prints the one it got, to pin with ``--sha256``), unpacks safely and prints the
``--dataset`` path the other commands take (``data.fetch`` says how). ``--from URL`` (or
``$VPR_EXPLORER_MIRROR``) fetches every file as ``URL/<file name>`` instead. A dataset
folder that exists already is skipped, not fetched again. Datasets served over rsync, by
a script or on request are refused by name with what to do.

Exit status: 0; 2 for a name the catalogue lacks (one ``error:`` line listing the names).
"""

from __future__ import annotations

import argparse

from vpr_explorer.data.catalogue import CATALOGUE, PublicDataset, find
from vpr_explorer.data.fetch import DEFAULT_DATA
from vpr_explorer.settings import DATA_ENV

#: the table's columns: heading and the value of a dataset
_COLUMNS = (
    ("name", lambda d: d.name),
    ("access", lambda d: d.access.value),
    ("layout", lambda d: d.layout.value),
    ("sha256", lambda d: d.checksums),
    ("title", lambda d: d.title),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``datasets``'s options: optional names to describe in full."""
    p.add_argument("names", nargs="*", metavar="NAME", help="describe these datasets in full (default: list every one)")


def table(datasets: tuple[PublicDataset, ...] = CATALOGUE) -> str:
    """The catalogue as aligned text columns, one dataset a line."""
    rows = [[head for head, _ in _COLUMNS]] + [[value(d) for _, value in _COLUMNS] for d in datasets]
    widths = [max(len(r[i]) for r in rows) for i in range(len(_COLUMNS) - 1)]
    return "\n".join("  ".join([*(c.ljust(w) for c, w in zip(r, widths)), r[-1]]).rstrip() for r in rows)


def describe(dataset: PublicDataset) -> str:
    """Every field of one dataset, one a line, its files with their URL and sha256 (or "not published")."""
    lines = [f"{dataset.name}: {dataset.title}", f"  home:     {dataset.home}", f"  licence:  {dataset.licence}",
             f"  size:     {dataset.size}", f"  layout:   {dataset.layout.value}", f"  access:   {dataset.access.value}",
             f"  folder:   {dataset.folder}"]
    for d in dataset.downloads:
        lines += [f"  file:     {d.file_name}", f"    url:    {d.url}",
                  f"    sha256: {d.sha256 or 'not published (fetch prints the one it gets)'}"]
    if dataset.how:
        lines.append(f"  how:      {dataset.how}")
    if dataset.source:
        lines.append(f"  source:   {dataset.source}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Print the catalogue, or the named datasets in full.

    Returns:
        0 (an unknown name raises ``VPRInputError``: exit 2).
    """
    if args.names:
        print("\n\n".join(describe(find(name)) for name in args.names))
        return 0
    print(table())
    print()
    print(f"{len(CATALOGUE)} datasets; `vpr-explorer datasets NAME` for one's home, licence, URLs and sha256; "
          "`vpr-explorer fetch NAME` downloads a 'download' one into "
          f"${DATA_ENV} (else {DEFAULT_DATA}).")
    return 0
