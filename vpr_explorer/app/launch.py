"""``vpr-explorer app``: serve the packaged explorer with Streamlit, from any directory.

``plan`` turns the command's options into a ``streamlit run`` of the packaged entry
script (``ENTRY``) and the environment it needs; ``run`` prints the URL and becomes that
server. The project's Streamlit settings travel as command-line flags (``SETTINGS``),
since Streamlit reads a ``.streamlit/config.toml`` only from the current directory; the
server binds 127.0.0.1 unless told otherwise. The dataset (with its layout and radius) and a
descriptor file reach the app through the environment (``DATASET_ENV``, ``LAYOUT_ENV``,
``RADIUS_ENV``, ``DESCRIPTORS_ENV``): every session opens them when its link names nothing
else, the browser that Streamlit opens included.

The data root (``DATA_ROOT_ENV``) travels the same way: a link or the Dataset page opens only
folders and descriptor files under it. ``--data-root`` names it; by default it is the folder
that holds ``--dataset`` (a dataset folder's parent, so that its neighbours open too; the
folder of a manifest ``.csv``; the dataset folder itself where its parent is the file
system's root), else ``VPR_EXPLORER_DATA``, else the current directory. A ``--dataset``
outside an explicit ``--data-root`` is refused; the ``--descriptors`` file is the operator's
and may lie anywhere (a link can only pick it by name). An ``--address`` other than loopback
prints a warning naming the root: anyone who can reach the port can browse it.

Imports no streamlit: the server is another program.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlencode

from vpr_explorer.app import (
    DATA_ROOT_ENV,
    DATASET_ENV,
    DESCRIPTORS_ENV,
    ENTRY,
    LAYOUT_ENV,
    RADIUS_ENV,
    data_root,
    started_view,
)
from vpr_explorer.cli.common import default_note
from vpr_explorer.data.groundtruth import DEFAULT_RADIUS
from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import DATA_ENV

DEFAULT_PORT = 8501
DEFAULT_ADDRESS = "127.0.0.1"
SETTINGS = {
    # No first-run e-mail prompt: the command must start the app unattended.
    "server.showEmailPrompt": "false",
    # Send nothing: the machines this runs on reach no network but the package registries.
    "browser.gatherUsageStats": "false",
    # An installed app does not change while it runs; a watcher would only poll site-packages.
    "server.fileWatcherType": "none",
}
"""Streamlit settings passed as ``--name value``; the checkout's ``.streamlit/config.toml`` holds the same ones."""


@dataclass(frozen=True)
class Launch:
    """What ``run`` starts.

    Attributes:
        argv: the server's command line (``python -m streamlit run ENTRY --flag value …``).
        env: variables added to the caller's environment for the server.
        url: the address to open, with the dataset and descriptor in its query.
        data_root: the folder the app serves (``DATA_ROOT_ENV``), resolved.
        warning: printed before the server starts (an address other machines can reach), or ``None``.
    """

    argv: tuple[str, ...]
    env: Mapping[str, str]
    url: str
    data_root: Path
    warning: str | None = None


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``app`` sub-command's options."""
    p.add_argument("--dataset", default=None,
                   help="dataset folder the app opens (or 'demo'); default: the demo route, another one is picked "
                        "on the Dataset page")
    p.add_argument("--layout", default=None, metavar="LAYOUT",
                   help="how the dataset is laid out (as for evaluate: traversals, prepared, database-queries, "
                        "vpr-bench, traversal-positions, manifest); default: detected, and changeable on the Dataset page")
    p.add_argument("--radius", type=float, default=None, metavar="METRES",
                   help="position-tagged layouts: a database image within this many metres is right"
                        + default_note(DEFAULT_RADIUS))
    p.add_argument("--descriptors", type=Path, default=None, metavar="FILE",
                   help="descriptors computed elsewhere (.npz, .npy, hloc .h5, or a VPR-methods-evaluation log "
                        "folder for a database-queries dataset), offered beside the extractors and opened first; "
                        "named by the file's (folder's) stem")
    p.add_argument("--data-root", type=Path, default=None, metavar="DIR",
                   help="the only folder whose datasets and descriptor files a link or the Dataset page may open "
                        "(symbolic links and .. resolved; nothing outside it is read or listed); default: the folder "
                        "holding --dataset (a dataset folder's parent, a manifest .csv's folder), else "
                        f"${DATA_ENV}, else the current folder")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="port to serve on")
    p.add_argument("--address", default=DEFAULT_ADDRESS,
                   help=f"address to bind: {DEFAULT_ADDRESS} is this machine only; 0.0.0.0 every interface, and then "
                        "anyone who can reach the port can browse the data root")
    p.add_argument("--headless", action="store_true",
                   help="do not open a browser (Streamlit's --server.headless true)")


def _dataset(text: str) -> str:
    if text == "demo":
        return text
    path = Path(text).expanduser()
    if not path.exists():
        raise VPRInputError(f"--dataset {text}: no such folder; give a dataset folder (one sub-folder per "
                            "traversal, or Place####_Cond##_G## images) or 'demo'")
    return str(path.resolve())  # the server's sessions and the printed link do not depend on this directory


def _descriptors(path: Path) -> Path:
    from vpr_explorer.descriptors.imported import descriptor_format
    from vpr_explorer.descriptors.registry import EXTRACTOR_NAMES
    from vpr_explorer.descriptors.vme_run import check_run_folder

    if path.expanduser().is_dir():  # a VPR-methods-evaluation run folder: both its .npy files there
        check_run_folder(path)
    else:
        descriptor_format(path)  # an unknown extension is refused here, not in every session
        if not path.expanduser().is_file():
            raise VPRInputError(f"--descriptors {path}: no such file; give a .npz, .npy or hloc .h5 file, or a "
                                "VPR-methods-evaluation log folder")
    if path.stem in EXTRACTOR_NAMES:
        raise VPRInputError(f"--descriptors {path}: its stem {path.stem!r} names a built-in descriptor; rename the "
                            "file (its stem names the descriptor in the app)")
    return path.expanduser().resolve()


def _data_root(given: Path | None, dataset: str | None) -> Path:
    """The folder the app serves: ``given``, else the one holding ``dataset`` (resolved), else the environment's."""
    if given is not None:
        root = Path(given).expanduser()
        if not root.is_dir():
            raise VPRInputError(f"--data-root {given}: no such folder; give the folder whose datasets and descriptor "
                                "files the app may open")
        root = root.resolve()
        if dataset is not None and dataset != "demo" and not Path(dataset).is_relative_to(root):
            raise VPRInputError(f"--dataset {dataset}: not under --data-root {root} (symbolic links and .. resolved); "
                                "give a dataset under it, or a --data-root that holds it")
        return root
    if dataset is not None and dataset != "demo":
        path = Path(dataset)
        holder = path.parent
        return path if path.is_dir() and holder == Path(holder.anchor) else holder
    value = os.environ.get(DATA_ENV, "")
    root = data_root({DATA_ENV: value})  # the app's own fallback: $VPR_EXPLORER_DATA, else the current folder
    if not root.is_dir():
        raise VPRInputError(f"{DATA_ENV}={value.strip()}: no such folder; point it at the folder holding the "
                            "datasets, or give --data-root")
    return root


def is_loopback(address: str) -> bool:
    """True for an address only this machine reaches: 127.0.0.0/8, ``::1`` or ``localhost``."""
    host = address.strip().strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name, or "" (every interface)
        return False


def exposure_warning(address: str, port: int, root: Path) -> str | None:
    """The line ``run`` prints when the server binds an address other machines may reach; ``None`` for loopback."""
    if is_loopback(address):
        return None
    return (f"warning: --address {address or '(every interface)'} is not loopback: anyone who can reach port {port} "
            f"can browse the data root {root} (every dataset and descriptor file under it); the default "
            f"{DEFAULT_ADDRESS} serves this machine only")


def _layout(text: str) -> str:
    from vpr_explorer.data.layouts import Layout

    try:
        return Layout(text).value
    except ValueError:
        raise VPRInputError(f"--layout {text}: choose one of {', '.join(x.value for x in Layout)}") from None


def _radius(value: float) -> str:
    import math

    if not math.isfinite(value) or value <= 0:
        raise VPRInputError(f"--radius {value:g}: must be a positive distance in metres, e.g. 25")
    return f"{value:g}"


def plan(*, dataset: str | None = None, descriptors: Path | None = None, port: int = DEFAULT_PORT,
         address: str = DEFAULT_ADDRESS, headless: bool = False, layout: str | None = None,
         radius: float | None = None, data_root: Path | str | None = None) -> Launch:
    """The server ``vpr-explorer app`` starts for these options.

    Raises:
        VPRInputError: a dataset folder, data root or descriptor file that is not there, a dataset
            outside the data root given, a layout that is not one, a radius that is not a positive
            number of metres, a descriptor file, layout or radius without its dataset, or a bad port.
    """
    if not 1 <= port <= 65535:
        raise VPRInputError(f"--port {port}: choose a port from 1 to 65535")
    env = {}
    if dataset is not None:
        env[DATASET_ENV] = _dataset(dataset)
    root = _data_root(None if data_root is None else Path(data_root), env.get(DATASET_ENV))
    env[DATA_ROOT_ENV] = str(root)
    for option, value, variable, check in (("layout", layout, LAYOUT_ENV, _layout),
                                           ("radius", radius, RADIUS_ENV, _radius)):
        if value is not None:
            if dataset is None:
                raise VPRInputError(f"--{option} {value}: give the --dataset it applies to too")
            env[variable] = check(value)
    if descriptors is not None:
        if dataset is None:
            raise VPRInputError(f"--descriptors {descriptors}: give the --dataset its rows describe too")
        env[DESCRIPTORS_ENV] = str(_descriptors(Path(descriptors)))
    flags = {**SETTINGS, "server.address": address, "server.port": str(port)}
    if headless:
        flags["server.headless"] = "true"
    argv = (sys.executable, "-m", "streamlit", "run", str(ENTRY),
            *(part for name, value in flags.items() for part in (f"--{name}", value)))
    host = DEFAULT_ADDRESS if address in ("", "0.0.0.0", "::") else address
    host = f"[{host}]" if ":" in host else host
    query = urlencode(started_view(env))
    return Launch(argv, env, f"http://{host}:{port}/" + (f"?{query}" if query else ""), root,
                  exposure_warning(address, port, root))


def run(args: argparse.Namespace) -> int:
    """``vpr-explorer app``: print the URL, then become the Streamlit server (until Ctrl-C)."""
    launch = plan(dataset=args.dataset, descriptors=args.descriptors, port=args.port, address=args.address,
                  headless=args.headless, layout=getattr(args, "layout", None), radius=getattr(args, "radius", None),
                  data_root=getattr(args, "data_root", None))
    print(f"VPR Threshold Explorer: {launch.url}\n  (serving {ENTRY.parent})\n"
          f"  data root: {launch.data_root} (a link opens only datasets and descriptor files under it; --data-root)",
          flush=True)
    if launch.warning is not None:
        print(launch.warning, flush=True)
    # exec, not a child process: Ctrl-C and a supervisor's SIGTERM reach the server itself.
    os.execve(launch.argv[0], list(launch.argv), {**os.environ, **launch.env})
    return 0  # not reached
