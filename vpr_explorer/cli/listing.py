"""``vpr-explorer list``: the dataset's images in the order descriptors are computed.

These are the rows of a ``.npy`` descriptor file to bring (``--descriptors FILE``), named as
a descriptor file names them: relative to the dataset's root.
"""

from __future__ import annotations

import argparse

from vpr_explorer.cli.common import check_radius_applies, check_radius_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``list``'s options: the dataset and its layout."""
    p.add_argument("--dataset", required=True, help="dataset folder (or a manifest .csv), or 'demo'")
    p.add_argument("--layout", default="auto", help="as for evaluate; auto detects it")
    p.add_argument("--radius", type=float, default=None, help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    """Print every image of the dataset, one relative path a line.

    Returns:
        0 (bad input raises ``VPRInputError``).
    """
    from vpr_explorer.descriptors.imported import relative_names
    from vpr_explorer.pipeline import open_dataset

    check_radius_option(args)
    dataset = open_dataset(args.dataset, args.layout, radius=args.radius)
    check_radius_applies(args, dataset)
    for name in relative_names(dataset.image_paths, dataset.root):  # the names a descriptor file matches
        print(name)
    return 0
