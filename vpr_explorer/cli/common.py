"""What several commands share: the dataset options, progress bars, the protocol options' checks.

Each command's module adds its options with the helpers here and reads them back with
:func:`protocol_options`, :func:`descriptor_name` (with :func:`hub_options`, the ``--hub-*``
flags of a ``hub:DIR[:ENTRY]`` descriptor) and the radius checks, so that an option means the
same and is refused with the same words in every command that takes it.

Every command's settings (its ``--json``, its report's header) record an extractor's
descriptors by name and, when ``--hub-*`` flags were given, those flags as typed, right after
the name (:func:`extractor_source`): ``"hub_options": "--hub-arg KEY=VALUE --hub-size W H"``;
without them the settings hold no such entry.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from vpr_explorer.data.groundtruth import DEFAULT_RADIUS, check_radius
from vpr_explorer.data.layouts import VPR_BENCH_GT, Layout, RetrievalDataset, radius_applies
from vpr_explorer.descriptors.hub import HUB_FLAGS, hub_settings
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceGeometry, Reading
from vpr_explorer.protocols.evaluation import Protocol
from vpr_explorer.protocols.options import MAX_RUNS, RUNS, SEED, UNKNOWN_SHARE
from vpr_explorer.settings import CACHE_ENV

#: the extractor a command runs when neither --descriptor nor --descriptors names one
DEFAULT_DESCRIPTOR = "efficientnet-lite0"
#: --cache-dir's help: where the cache is when the option is not given (``settings.cache_root``)
CACHE_HELP = f"descriptor cache folder (default: ${CACHE_ENV}, else ~/.cache/vpr_explorer)"

#: The paper and open-set protocols' options: name -> (the protocols that read it, its value when
#: not given: ``protocols.options``' default). Their argparse default is None ("not given"), so
#: that one the chosen protocol would ignore is refused (:func:`protocol_options`); each command
#: adds its own to this table.
SPLIT_OPTIONS = {
    "runs": ((Protocol.PAPER, Protocol.OPEN_SET), RUNS),
    "seed": ((Protocol.PAPER, Protocol.OPEN_SET), SEED),
    "cross_condition": ((Protocol.PAPER, Protocol.OPEN_SET), False),
    "unknown_share": ((Protocol.OPEN_SET,), UNKNOWN_SHARE),
}


def shown(value) -> str:
    """A default as a help text writes it: numbers in their shortest form, a list's items spaced."""
    if isinstance(value, (list, tuple)):
        return " ".join(map(shown, value))
    return f"{value:g}" if isinstance(value, float) else str(value)


def default_note(value) -> str:
    """`` (default: VALUE)``, as :class:`HelpFormatter` appends it, for an option whose argparse default is None."""
    return f" (default: {shown(value)})".replace("%", "%%")


#: reStructuredText's inline literals (two backticks each side) and roles (``:func:`` and the like, ``~`` too)
RST_LITERAL = re.compile(r"``(.+?)``|:[a-z]+(?::[a-z]+)?:`~?(.+?)`")


def plain(text: str) -> str:
    """``text`` as a terminal shows it: reStructuredText's literals and roles become single-backtick words."""
    return RST_LITERAL.sub(lambda m: f"`{m.group(1) or m.group(2)}`", text)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's help with each option's default appended where there is one to state.

    A required option, a switch (default False) and an option whose default is None (not
    given: the command decides, and the option's help says how) get none appended. Help,
    descriptions and epilogs print reStructuredText's literals and roles with single backticks
    (:func:`plain`), so a text shared with a docstring reads plainly in a terminal.
    """

    def _format_text(self, text: str) -> str:
        return super()._format_text(plain(text))

    def _expand_help(self, action: argparse.Action) -> str:
        return plain(super()._expand_help(action))

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if action.required or default is None or default is False or default is argparse.SUPPRESS:
            return text
        if "%(default)" in text or not action.option_strings:
            return text
        return text + default_note(default)


class Bars:
    """The progress bars drawn on stderr, so that an ``error:`` line never lands on one's line.

    Attributes:
        open: the bars not yet finished (tqdm objects), in the order they were drawn.
        drawn: whether a bar was drawn since the last :meth:`reset`.
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget the bars: a command starts with none."""
        self.open: list = []
        self.drawn = False

    def clear(self) -> None:
        """Close the unfinished bars and end their line, so that what follows starts a line of its own."""
        while self.open:
            self.open.pop().close()
        if self.drawn:
            sys.stderr.write("\n")
            sys.stderr.flush()
        self.reset()


#: the bars of the command running in this process (``parser.run_command`` resets and clears them)
BARS = Bars()


def bar(desc: str):
    """A progress callback drawing a tqdm bar on stderr, registered in :data:`BARS`.

    Args:
        desc: the bar's label, e.g. ``"descriptors"``.

    Returns:
        ``update(done, total, *message)``: the bar shows ``done`` of ``total``; a first
        message, when given and not empty, goes beside it.
    """
    from tqdm import tqdm

    state: dict = {}

    def update(done: int, total: int, *message):
        if "bar" not in state:
            BARS.drawn = True  # before the bar exists: Ctrl-C may land while it is being drawn
            state["bar"] = tqdm(total=total, desc=desc, unit="", file=sys.stderr, leave=False, dynamic_ncols=True)
            BARS.open.append(state["bar"])
        progress = state["bar"]
        if message and message[0]:
            progress.set_postfix_str(str(message[0]), refresh=False)
        progress.update(done - progress.n)
        if done >= total and progress in BARS.open:
            progress.close()
            BARS.open.remove(progress)

    return update


def number(text: str) -> int | float:
    """A group/step value: a whole number of frames, or metres (which may have a fraction).

    Raises:
        argparse.ArgumentTypeError: ``text`` is not a number (argparse names the option).
    """
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    return int(value) if value.is_integer() and abs(value) < 2**63 else value


def add_dataset_args(p: argparse.ArgumentParser, *, places: bool = True) -> None:
    """The options of every command that reads a dataset and its descriptors.

    Args:
        p: the command's parser.
        places: add ``--group``, ``--step`` and ``--reading`` (one value each); a command that
            takes several of each adds its own instead.
    """
    p.add_argument("--dataset", required=True,
                   help="dataset folder (or a manifest .csv), or 'demo' for the built-in route")
    p.add_argument("--layout", choices=[x.value for x in Layout], default=Layout.AUTO.value,
                   help="how the dataset is laid out: aligned traversal folders, prepared Place####_Cond##_G## "
                        "images, database/ + queries/ with @UTM@ names, VPR-Bench ref/ + query/ + "
                        "ground_truth_new.npy, traversal folders with positions.csv, or a manifest CSV; auto "
                        "detects it")
    p.add_argument("--radius", type=float, default=None,
                   help="position-tagged layouts: a database image within this many metres is right"
                        + default_note(DEFAULT_RADIUS))
    p.add_argument("--geometry", choices=[g.value for g in PlaceGeometry], default=None,
                   help="database/queries layouts: group/step count database images in order (frames), or metres "
                        "along the route (route) or of a lattice over the plane (lattice); default route or lattice "
                        "where the layout has positions, else frames")
    if places:
        p.add_argument("--group", type=number, default=3,
                       help="consecutive frames (or metres, see --geometry) per place")
        p.add_argument("--step", type=number, default=10, help="frames (or metres) from one place to the next")
        p.add_argument("--reading", choices=[r.value for r in Reading], default=Reading.STRIDE.value,
                       help="stride: a place starts every STEP frames (authors' code); skip: take GROUP, skip STEP "
                            "(paper text)")
    p.add_argument("--descriptor", default=None,
                   help="descriptor name, or hub:DIR[:ENTRY] for a model of a local torch.hub repository"
                        + default_note(DEFAULT_DESCRIPTOR))
    add_hub_args(p)
    p.add_argument("--descriptors", type=Path, default=None, metavar="FILE",
                   help="descriptors computed elsewhere: .npz (names, descriptors), .npy (rows in 'vpr-explorer list' "
                        "order, or names in FILE.txt) or an hloc global-feature .h5; named by the file's stem; or a "
                        "VPR-methods-evaluation log folder (database_descriptors.npy, queries_descriptors.npy) "
                        "for a database-queries dataset, named by the folder's stem")
    p.add_argument("--names", type=Path, default=None, metavar="FILE",
                   help="with a .npy --descriptors: the file naming its rows (one image path per line)")
    p.add_argument("--cache-dir", type=Path, default=None, help=CACHE_HELP)
    p.add_argument("--dtype", choices=["float32", "float16"], default="float32",
                   help="descriptor precision in memory and in the cache: float16 halves the descriptor memory "
                        "and disk, at about 1e-3 relative error in scores")


def add_hub_args(p: argparse.ArgumentParser) -> None:
    """The options of a ``hub:DIR[:ENTRY]`` descriptor (``descriptors.hub``), read back by :func:`hub_options`."""
    from vpr_explorer.descriptors.preprocess import Normalisation

    p.add_argument("--hub-arg", action="append", default=None, metavar="KEY=VALUE",
                   help="with a hub:... descriptor: a keyword argument of the hub entry, repeatable; VALUE is read "
                        "as None, true/false, an int, a float, a 'quoted' string, else the string as written")
    p.add_argument("--hub-size", type=int, nargs=2, default=None, metavar=("W", "H"),
                   help="with a hub:... descriptor: resize every image to W x H (aspect not kept); default: the "
                        "known model's input (MegaLoc, SALAD, BoQ 322 x 322 or 384 x 384), needed for any other")
    p.add_argument("--hub-short-side", type=int, default=None, metavar="N",
                   help="with a hub:... descriptor: resize the shorter side to N, aspect kept (CosPlace and "
                        "EigenPlaces: 480), instead of --hub-size")
    p.add_argument("--hub-normalisation", choices=[n.value for n in Normalisation], default=None,
                   help="with a hub:... descriptor: pixel normalisation (default: the known model's, else imagenet)")


def hub_options(args: argparse.Namespace, descriptors: list[str] | None = None) -> dict:
    """``get_extractor``'s options from the ``--hub-*`` flags given (hashable values: Ray keys its models by them).

    Args:
        args: the parsed command line.
        descriptors: the descriptor names the flags go to; default ``[args.descriptor]``.

    Returns:
        Option name -> value, for the flags given (``{}`` for none).

    Raises:
        VPRInputError: a ``--hub-*`` flag where no descriptor is ``hub:...``, naming the flags.
    """
    from vpr_explorer.descriptors.hub import is_hub_name

    given = {"hub_args": None if args.hub_arg is None else tuple(args.hub_arg),
             "input_size": None if args.hub_size is None else tuple(args.hub_size),
             "short_side": args.hub_short_side, "normalisation": args.hub_normalisation}
    given = {k: v for k, v in given.items() if v is not None}
    names = [args.descriptor] if descriptors is None else list(descriptors)
    if given and not any(is_hub_name(name) for name in names):
        if descriptors is not None:
            this = f"--descriptors {' '.join(names)}" if names else "no --descriptors"
        elif args.descriptor is not None:
            this = f"--descriptor {args.descriptor}"
        elif getattr(args, "descriptors", None) is not None:
            this = f"--descriptors {args.descriptors}"
        else:
            this = f"the default --descriptor {DEFAULT_DESCRIPTOR}"
        where = "hub:DIR[:ENTRY] descriptors" if descriptors is not None else "--descriptor hub:DIR[:ENTRY]"
        raise VPRInputError(f"{', '.join(HUB_FLAGS[k] for k in given)} apply to {where} only, and this is {this}: "
                            "drop them, or name a hub repository")
    return given


def extractor_source(args: argparse.Namespace) -> dict[str, str]:
    """What the settings record of an extractor's descriptors beside its name: the ``--hub-*`` flags given.

    Returns:
        ``{"hub_options": "--hub-arg KEY=VALUE --hub-size W H"}``: the flags given, in
        ``HUB_FLAGS``' order, as a shell takes them (``descriptors.hub.hub_settings``); ``{}`` when
        none was given.

    Raises:
        VPRInputError: a ``--hub-*`` flag without ``--descriptor hub:...`` (:func:`hub_options`).
    """
    return hub_settings(hub_options(args))


def add_split_args(p: argparse.ArgumentParser, splits: str = "random splits") -> None:
    """The options of :data:`SPLIT_OPTIONS`: ``--runs``, ``--seed``, ``--cross-condition``, ``--unknown-share``.

    Args:
        p: the command's parser.
        splits: what ``--runs`` counts, e.g. ``"random splits per cell"``.
    """
    runs, seed, unknown_share = (SPLIT_OPTIONS[name][1] for name in ("runs", "seed", "unknown_share"))
    p.add_argument("--runs", type=int, default=None,
                   help=f"paper and open-set protocols: {splits} (the paper's R), at most {MAX_RUNS}"
                        + default_note(runs))
    p.add_argument("--seed", type=int, default=None,
                   help="paper and open-set protocols: seed of the splits" + default_note(seed))
    p.add_argument("--cross-condition", action="store_true", default=None,
                   help="paper and open-set protocols: score each query only against database images of other "
                        "traversals")
    p.add_argument("--unknown-share", type=float, default=None,
                   help="open-set protocol: share of places held out" + default_note(unknown_share))


def protocol_options(args: argparse.Namespace, options: dict) -> dict:
    """The options ``args.protocol`` reads, defaults filled in; one it would ignore is refused, named.

    Args:
        args: the parsed command line; ``args.protocol`` names the protocol.
        options: option name -> (the protocols that read it, its value when not given), e.g.
            :data:`SPLIT_OPTIONS` with the command's own.

    Returns:
        Option name -> its value, for every option of ``options``.

    Raises:
        VPRInputError: an option was given that ``args.protocol`` does not read.
    """
    protocol = Protocol(args.protocol)
    values = {}
    for name, (protocols, default) in options.items():
        value = getattr(args, name)
        if value is not None and protocol not in protocols:
            option = "--" + name.replace("_", "-")
            owners = " and ".join(p.value for p in protocols)
            raise VPRInputError(
                f"{option} applies to the {owners} protocol{'s' if len(protocols) > 1 else ''} only, and this is "
                f"--protocol {protocol.value}: drop {option}, or pick --protocol {protocols[0].value}"
            )
        values[name] = default if value is None else value
    return values


def descriptor_name(args: argparse.Namespace) -> str:
    """The descriptor's name: ``--descriptors FILE``'s stem (a run folder's too), else ``--descriptor``, else
    :data:`DEFAULT_DESCRIPTOR`.

    The ``--hub-*`` flags are checked here too (:func:`hub_options`), so that one beside a
    descriptor that is not ``hub:...`` is refused before anything is read.

    Raises:
        VPRInputError: both ``--descriptor`` and ``--descriptors`` were given, ``--names``
            without ``--descriptors``, or a ``--hub-*`` flag without ``--descriptor hub:...``.
    """
    hub_options(args)
    if args.descriptors is not None:
        if args.descriptor is not None:
            raise VPRInputError(f"--descriptor {args.descriptor} and --descriptors {args.descriptors}: give one "
                                "(a file of descriptors computed elsewhere, or an extractor to compute them here)")
        return args.descriptors.stem
    if args.names is not None:
        raise VPRInputError("--names goes with a .npy --descriptors FILE")
    return args.descriptor or DEFAULT_DESCRIPTOR


def check_radius_option(args: argparse.Namespace) -> float | None:
    """``--radius`` when given: a positive number of metres (``groundtruth.check_radius``), else None.

    Raises:
        VPRInputError: ``--radius`` is not a positive number of metres.
    """
    return None if args.radius is None else check_radius(args.radius, "radius")


def check_radius_applies(args: argparse.Namespace, dataset) -> None:
    """Refuse ``--radius`` for a dataset whose ground truth no radius makes (VPR-Bench, a manifest's place ids).

    Args:
        args: the parsed command line.
        dataset: the opened dataset (``Dataset`` or ``RetrievalDataset``).

    Raises:
        VPRInputError: ``--radius`` was given and ``dataset`` takes its ground truth from elsewhere.
    """
    if args.radius is None or (isinstance(dataset, RetrievalDataset) and radius_applies(dataset)):
        return
    if not isinstance(dataset, RetrievalDataset):
        where = "the frame index of aligned traversals"
    elif dataset.layout is Layout.VPR_BENCH:
        where = VPR_BENCH_GT
    elif dataset.layout is Layout.MANIFEST:
        where = "its place column (the same place id)"
    else:
        where = dataset.ground_truth.description
    layout = dataset.layout.value if isinstance(dataset, RetrievalDataset) else "traversal folders"
    raise VPRInputError(f"--radius applies to position-tagged layouts; {args.dataset} is {layout}, which takes its "
                        f"ground truth from {where}: drop --radius")


def refuse_retrieval_options(args: argparse.Namespace, reason: str) -> None:
    """Refuse ``--radius`` and ``--geometry``, which apply to database/queries layouts, saying why not here.

    Args:
        args: the parsed command line.
        reason: why they do not apply, e.g. ``"a sweep reads aligned traversal folders"``.

    Raises:
        VPRInputError: one of them was given.
    """
    for option in ("radius", "geometry"):
        if getattr(args, option) is not None:
            raise VPRInputError(f"--{option} applies to database/queries layouts; {reason}")


def retrieval_dataset(args: argparse.Namespace) -> RetrievalDataset | None:
    """The database/queries dataset ``--dataset``/``--layout`` name, or ``None`` for aligned traversal folders.

    Args:
        args: the parsed command line (``--dataset``, ``--layout``, ``--radius``, ``--geometry``,
            ``--database``, ``--queries``).

    Returns:
        The dataset read in its layout, or ``None`` when it is aligned traversal folders (or
        prepared places), whose places are group/step over frames.

    Raises:
        VPRInputError: ``--radius`` or ``--geometry`` for aligned traversal folders, a radius the
            layout does not read, or a dataset that cannot be read.
    """
    from vpr_explorer.data.layouts import RETRIEVAL_LAYOUTS, detect_layout
    from vpr_explorer.pipeline import DEMO, open_dataset

    check_radius_option(args)
    layout = Layout(args.layout)
    path = Path(args.dataset).expanduser()
    if layout is Layout.AUTO and args.dataset != DEMO and path.exists():
        layout = detect_layout(path)
    if layout not in RETRIEVAL_LAYOUTS:
        read_as = "traversal folders" if layout in (Layout.AUTO, Layout.TRAVERSALS) else f"{layout.value} folders"
        refuse_retrieval_options(args, f"{args.dataset} is read as {read_as}, whose places are group/step over "
                                       "frames")
        return None
    dataset = open_dataset(args.dataset, layout.value, radius=args.radius, database=args.database,
                           queries=args.queries)
    check_radius_applies(args, dataset)
    return dataset


def value_descriptors(args: argparse.Namespace, value, descriptor: str):
    """The value's descriptors (database rows first): extracted through the cache, or read from ``--descriptors``.

    Returns:
        ``(descriptors, name, source, notes)``: the ``(n_images, D)`` matrix, the descriptor's
        name, what the settings record of where they came from (the file's path and sha256, or
        an extractor's ``--hub-*`` flags: :func:`extractor_source`) and what reading the file noted.
    """
    from vpr_explorer.data.aligned import value_rows
    from vpr_explorer.pipeline import dataset_descriptors, imported_descriptors

    if args.descriptors is None:
        desc = dataset_descriptors(value, descriptor, cache_root=args.cache_dir, progress=bar("descriptors"),
                                   dtype=args.dtype, options=hub_options(args))
        return desc, descriptor, extractor_source(args), ()
    # a file lists the dataset's images ('vpr-explorer list'): aligned traversals' rows move to the value's order
    owner = value if value.aligned is None else value.aligned
    imp = imported_descriptors(owner, args.descriptors, names_file=args.names, dtype=args.dtype)
    rows = value_rows(value) if value.aligned is not None else None
    desc = imp.descriptors if rows is None else imp.descriptors[rows]
    return desc, imp.name, imp.settings(), tuple(f"{args.descriptors.name}: {note}" for note in imp.notes)

@dataclass(frozen=True)
class AlignedValue:
    """Aligned traversals read as one database/queries value (``aligned_value``).

    Attributes:
        value: the ``RetrievalDataset``: the query traversal against the database traversals.
        database: the database traversals' names; query: the query traversal's name.
        tolerance: right within ± this many frames of the query's frame.
        how: "as given", or how the default traversals were chosen (``pipeline.traversal_direction``).
        defaults: the default database traversals (before ``first_database_only`` kept one).
    """

    value: RetrievalDataset
    database: tuple[str, ...]
    query: str
    tolerance: int
    how: str
    defaults: tuple[str, ...]


def aligned_value(args: argparse.Namespace, tolerance: int, *, first_database_only: bool = False) -> AlignedValue:
    """``--dataset``'s aligned traversals as a database/queries value: ``--queries`` against ``--database``.

    Args:
        args: the parsed command line (``dataset``, ``layout``, ``database``, ``queries``).
        tolerance: frames of slack (checked against the dataset's frames).
        first_database_only: keep only the first database traversal (rules that read the
            database as one route).

    Raises:
        VPRInputError: a tolerance outside 0 to the number of frames, or what opening the dataset raises.
    """
    from vpr_explorer.data.aligned import database_queries
    from vpr_explorer.pipeline import default_traversals, open_dataset, traversal_direction
    from vpr_explorer.protocols.options import check_whole

    aligned = open_dataset(args.dataset, args.layout)
    tolerance = check_whole("--tolerance", tolerance, low=0, high=aligned.n_frames,
                            why=f" (frames of slack; {aligned.name!r} has {aligned.n_frames:,} frames)")
    db, q = default_traversals(aligned, args.database, args.queries)
    how = "as given" if args.database or args.queries else traversal_direction(aligned, db, q)
    kept = db[:1] if first_database_only else db
    value = database_queries(aligned, q, database=kept, tolerance=tolerance)
    return AlignedValue(value, tuple(aligned.traversals[t] for t in kept), aligned.traversals[q], tolerance, how,
                        tuple(aligned.traversals[t] for t in db))


def write_text(path: Path | None, text: str, option: str) -> None:
    """Write ``text`` to ``path`` (nothing when None) and say so.

    Args:
        path: the file an option named, or None when it was not given.
        text: the file's content.
        option: the option that named it, e.g. ``"--json"``.

    Raises:
        VPRInputError: the file cannot be written.
    """
    if path is None:
        return
    try:
        path.write_text(text)
    except OSError as exc:
        raise VPRInputError(f"{option} {path}: cannot write ({exc.strerror}); pick a writable path") from exc
    print(f"wrote {path}")
