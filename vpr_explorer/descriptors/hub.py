"""Any torch.hub model as an extractor: the descriptor name ``hub:DIR[:ENTRY]``.

``DIR`` is a local torch.hub repository: a clone, or the folder ``torch.hub.load`` unpacked
into its cache (``$TORCH_HOME/hub/<owner>_<repo>_<branch>``, e.g.
``~/.cache/torch/hub/gmberton_MegaLoc_main``). The model is
``torch.hub.load(DIR, ENTRY, source="local", **hub_args)``: put in eval mode on the
extractor's device, fed ``(B, 3, H, W)`` float32 batches, its ``(B, D)`` output L2-normalised
by the pipeline. A tuple or list output gives its first element (Bag-of-Queries returns
``(descriptor, attentions)``).

``ENTRY`` left out: the one public function (a top-level ``def`` whose name does not start
with ``_``) that ``hubconf.py`` defines; with none or several, the name is refused, listing
them. The entries are read from ``hubconf.py``'s syntax tree, without running it.

Hub arguments (``--hub-arg key=value``, repeatable; ``hub_args`` in code: a mapping, or
``key=value`` strings) are read, in this order: ``None`` / ``none`` / ``null`` -> ``None``;
``true`` / ``false`` (any case) -> bool; digits with an optional sign -> int; a decimal or
exponent number (``0.5``, ``1e-3``) -> float; a value in single or double quotes -> the
string inside (``"'1'"`` is the string ``1``); anything else -> the string as written. A key
is a Python identifier, given once. When the entry's signature (read from the syntax tree)
takes no ``**kwargs``, an unknown or missing argument is refused before anything runs.

Input: the whole frame resized bilinearly to ``input_size`` = ``(width, height)`` (aspect
not kept), or its shorter side to ``short_side`` (aspect kept), then normalised
(``imagenet`` default, ``unit``, ``signed``): a
:class:`~vpr_explorer.descriptors.preprocess.DeviceRecipe`. Models the field publishes this
way are recognised by the folder's name (case ignored) and entry, and get their authors'
input unless one is given (:data:`KNOWN_MODELS`):

====================  =====================  ======================  =========  =========  =====
repository            entry                  arguments               input      normalise  patch
====================  =====================  ======================  =========  =========  =====
gmberton/MegaLoc      ``get_trained_model``  none                    322 x 322  imagenet   14
serizba/salad         ``dinov2_salad``       its defaults            322 x 322  imagenet   14
Bag-of-Queries        ``get_trained_boq``    backbone_name=resnet50  384 x 384  imagenet   --
Bag-of-Queries        ``get_trained_boq``    backbone_name=dinov2    322 x 322  imagenet   14
gmberton/cosplace     ``get_trained_model``  any                     short 480  imagenet   --
gmberton/eigenplaces  ``get_trained_model``  any                     short 480  imagenet   --
====================  =====================  ======================  =========  =========  =====

(Bag-of-Queries: ``amaralibey/Bag-of-Queries``, whose README resizes bicubically; here it is
bilinear, as everywhere else. CosPlace and EigenPlaces: the shorter side at 480 as the
built-in ``cosplace`` / ``eigenplaces`` extractors feed them.) Any other model needs
``input_size`` or ``short_side``. A DINOv2 model's sides must be multiples of its patch,
14: the table's patch, else the ``patch_size`` of the loaded model's first module that has
one (DINOv2's, timm's ``PatchEmbed``), is checked, and a size that is not is refused with
the nearest multiples (so is ``short_side``, whose long side is not fixed).

Cache key ``hub.<folder>.<entry>-<version>``: the version holds a sha256 over the
repository's identity (the git commit when ``DIR`` is a git checkout, read from
``.git/HEAD`` and its ref without running git; and always the content of every ``.py``
file under ``DIR``, hidden folders and ``__pycache__`` left out, so an uncommitted edit
counts too), the entry, its arguments (sorted by key, with their types), the input size or
short side and the normalisation. Weights the entry downloads are named by their URL in
that code, so they are covered; a checkpoint replaced under the same name is not.

Running a hubconf runs the repository's code in this process, as a registered entry point
does (:mod:`~vpr_explorer.descriptors.custom`): that is the user's choice when they name
``DIR``. A hub path must therefore only ever come from the user (the command line, code,
the models settings file): never from a dataset folder, a manifest or a URL parameter of the
app (the app refuses a ``hub:`` name it is given). torch.hub imports the repository's own
modules by their plain names (``megaloc_model``...), so two repositories
with a module of the same name cannot both be loaded in one process; with Ray, ``DIR``
must be at the same path on every node, as the images are.

This module imports no torch until a model is built, so naming a hub model stays cheap.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import re
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from vpr_explorer.descriptors.base import Extractor
from vpr_explorer.descriptors.preprocess import INPUT_SIDE_RANGE, RECIPE_VERSION, DeviceRecipe, Normalisation
from vpr_explorer.errors import VPRInputError

PREFIX = "hub:"
HUBCONF = "hubconf.py"
#: ``get_extractor("hub:...", ...)``'s options besides the runtime ones (device, precision).
OPTIONS = ("hub_args", "input_size", "short_side", "normalisation")
#: the command-line flag of each hub option (:data:`OPTIONS`), in the order :func:`hub_flags` writes them
HUB_FLAGS = {"hub_args": "--hub-arg", "input_size": "--hub-size", "short_side": "--hub-short-side",
             "normalisation": "--hub-normalisation"}
#: the settings key of a hub model's options, written as flags (:func:`hub_settings`)
HUB_SETTING = "hub_options"
DINOV2_PATCH = 14
#: Characters of the folder's name kept in the cache key; others become ``_``.
_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]")
_NAME_CHARS = 48
_SHA = re.compile(r"^[0-9a-f]{40}([0-9a-f]{24})?$")
_INT = re.compile(r"^[+-]?\d+$")
_FLOAT = re.compile(r"^[+-]?(\d+\.\d*|\.\d+|\d+)([eE][+-]?\d+)?$")
_ENTRY = re.compile(r"^[A-Za-z_]\w*$")

HubValue = None | bool | int | float | str


@dataclass(frozen=True)
class KnownModel:
    """A published hub model's input, as its authors feed it.

    Attributes:
        repository: matched, case ignored, within the folder's name (``gmberton_MegaLoc_main``).
        entry: its hubconf entry.
        input_size, short_side: the resize (one of them).
        patch: the ViT patch its sides must be multiples of, or ``None``.
        arg, value: the row applies when hub argument ``arg`` is ``value`` (``None``: always).
        default: the row applies too when ``arg`` is not given (it is the entry's default).
    """

    repository: str
    entry: str
    input_size: tuple[int, int] | None = None
    short_side: int | None = None
    normalisation: Normalisation = Normalisation.IMAGENET
    patch: int | None = None
    arg: str | None = None
    value: HubValue = None
    default: bool = False

    def applies(self, folder: str, entry: str, args: Mapping[str, HubValue]) -> bool:
        if self.repository not in folder.lower() or entry != self.entry:
            return False
        if self.arg is None:
            return True
        return args[self.arg] == self.value if self.arg in args else self.default


KNOWN_MODELS: tuple[KnownModel, ...] = (
    KnownModel("megaloc", "get_trained_model", input_size=(322, 322), patch=DINOV2_PATCH),
    KnownModel("salad", "dinov2_salad", input_size=(322, 322), patch=DINOV2_PATCH),
    KnownModel("bag-of-queries", "get_trained_boq", input_size=(384, 384), arg="backbone_name", value="resnet50",
               default=True),
    KnownModel("bag-of-queries", "get_trained_boq", input_size=(322, 322), patch=DINOV2_PATCH,
               arg="backbone_name", value="dinov2"),
    KnownModel("cosplace", "get_trained_model", short_side=480),
    KnownModel("eigenplaces", "get_trained_model", short_side=480),
)


@dataclass(frozen=True)
class EntrySignature:
    """An entry's parameters as ``hubconf.py`` writes them.

    Attributes:
        params: ``(name, default as written or None when required)``, keyword-passable ones.
        var_keyword: whether it takes ``**kwargs`` (then arguments are not checked ahead).
    """

    params: tuple[tuple[str, str | None], ...]
    var_keyword: bool

    def describe(self) -> str:
        shown = [name if default is None else f"{name}={default}" for name, default in self.params]
        return ", ".join(shown + (["**kwargs"] if self.var_keyword else [])) or "no arguments"


@dataclass(frozen=True)
class HubModel:
    """A hub model, validated by :func:`hub_model`.

    Attributes:
        repo: the repository folder, resolved.
        entry: the hubconf entry.
        args: its keyword arguments, sorted by key.
        input_size: ``(width, height)``, or ``None`` with ``short_side``.
        short_side: the shorter side's pixels, or ``None`` with ``input_size``.
        normalisation: pixel normalisation.
        patch: the patch the sides must be multiples of when known ahead (the table's).
    """

    repo: Path
    entry: str
    args: tuple[tuple[str, HubValue], ...]
    input_size: tuple[int, int] | None
    short_side: int | None
    normalisation: Normalisation
    patch: int | None

    @property
    def name(self) -> str:
        """``hub.<folder>.<entry>``: the extractor's name, its cache folders' prefix."""
        return _extractor_name(self.repo, self.entry)

    @property
    def call(self) -> str:
        """``ENTRY(key=value, ...)`` of ``DIR``, for messages."""
        shown = ", ".join(f"{k}={v!r}" for k, v in self.args)
        return f"{self.entry}({shown}) of {self.repo}"

    @property
    def resize(self) -> str:
        if self.input_size is not None:
            return f"{self.input_size[0]}x{self.input_size[1]}"
        return f"s{self.short_side}"


# ------------------------------------------------------------------ names and arguments


def _extractor_name(repo: Path, entry: str) -> str:
    return f"hub.{_UNSAFE.sub('_', repo.name)[:_NAME_CHARS] or 'repo'}.{entry}"


def is_hub_name(name: object) -> bool:
    """Whether ``name`` is a ``hub:...`` descriptor name."""
    return isinstance(name, str) and name.startswith(PREFIX)


def split_hub_name(name: str) -> tuple[Path, str | None]:
    """``hub:DIR[:ENTRY]`` -> ``(DIR resolved, ENTRY or None)``.

    The text after the last ``:`` is the entry when it is a Python identifier and something
    precedes it; otherwise the whole rest is ``DIR``.

    Raises:
        VPRInputError: no folder after ``hub:``.
    """
    rest = name[len(PREFIX):] if is_hub_name(name) else ""
    head, sep, tail = rest.rpartition(":")
    folder, entry = (head, tail) if sep and head and _ENTRY.match(tail) else (rest, None)
    if not folder.strip():
        raise VPRInputError(f"descriptor {name!r}: give hub:DIR or hub:DIR:ENTRY, DIR a torch.hub repository folder")
    return Path(folder).expanduser().resolve(), entry


def parse_hub_value(text: str) -> HubValue:
    """One ``--hub-arg`` value by the rules of the module docstring."""
    if text in ("None", "none", "null"):
        return None
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    if _INT.match(text):
        return int(text)
    if _FLOAT.match(text):
        return float(text)
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    return text


def hub_arguments(value: object) -> tuple[tuple[str, HubValue], ...]:
    """``hub_args`` as sorted ``(key, value)`` pairs: from a mapping, ``key=value`` strings or pairs.

    Raises:
        VPRInputError: a key that is not an identifier or given twice, a string without
            ``=``, a value that is not None, bool, int, float or str.
    """
    if value is None:
        return ()
    if isinstance(value, Mapping):
        pairs = list(value.items())
    elif isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise VPRInputError(f"hub_args={value!r}: give a mapping or a list of key=value strings")
    else:
        pairs = []
        for item in value:
            if isinstance(item, str):
                key, sep, text = item.partition("=")
                if not sep:
                    raise VPRInputError(f"--hub-arg {item!r}: write key=value (e.g. backbone=ResNet50)")
                pairs.append((key.strip(), parse_hub_value(text.strip())))
            elif isinstance(item, (tuple, list)) and len(item) == 2:
                pairs.append(tuple(item))
            else:
                raise VPRInputError(f"hub_args item {item!r}: give key=value strings or (key, value) pairs")
    seen: dict[str, HubValue] = {}
    for key, val in pairs:
        if not isinstance(key, str) or not key.isidentifier():
            raise VPRInputError(f"--hub-arg {key!r}: the key must be a Python identifier (an argument of the entry)")
        if key in seen:
            raise VPRInputError(f"--hub-arg {key}: given twice; give each argument once")
        if val is not None and not isinstance(val, (bool, int, float, str)):
            raise VPRInputError(f"--hub-arg {key}={val!r}: a value must be None, a bool, a number or a string")
        seen[key] = val
    return tuple(sorted(seen.items()))


def hub_flags(options: Mapping[str, object]) -> list[str]:
    """``get_extractor``'s hub options as the ``--hub-*`` flags that give them, in :data:`HUB_FLAGS`' order.

    ``--hub-arg KEY=VALUE`` once per argument (``hub_args``: ``key=value`` strings as given, or
    ``(key, value)`` pairs or a mapping, each value written so that ``--hub-arg`` reads it back),
    ``--hub-size W H``, ``--hub-short-side N``, ``--hub-normalisation NAME``. An option that is
    absent or None gives none.

    Args:
        options: option name (``HUB_FLAGS``' keys) -> value, e.g. ``{"input_size": (64, 48)}``.

    Returns:
        The command-line words, e.g. ``["--hub-size", "64", "48"]``; empty for no options.
    """
    argv: list[str] = []
    for name, flag in HUB_FLAGS.items():
        value = options.get(name)
        if value is None:
            continue
        if name == "hub_args":
            items = value.items() if isinstance(value, Mapping) else value
            argv += [word for item in items for word in (flag, _hub_arg(item))]
        else:
            argv += [flag, *map(str, value if isinstance(value, (tuple, list)) else (value,))]
    return argv


def _hub_arg(item: str | tuple[str, object]) -> str:
    """One hub argument as ``--hub-arg`` takes it: a ``key=value`` string as given, a pair as ``key=value``.

    A string value that :func:`parse_hub_value` would read as something else (``1``,
    ``true``, ``None``, a quoted word) is quoted, so that it reads back as the same string.
    """
    if isinstance(item, str):
        return item
    key, value = item
    text = "None" if value is None else str(value).lower() if isinstance(value, bool) else str(value)
    if isinstance(value, str) and parse_hub_value(text) != value:
        text = f"'{value}'"
    return f"{key}={text}"


def hub_settings(options: Mapping[str, object]) -> dict[str, str]:
    """The settings entry of a hub model's options: ``{"hub_options": FLAGS}``, or ``{}`` for none.

    ``FLAGS`` is :func:`hub_flags` as a shell would take them (``shlex.join``), e.g.
    ``"--hub-arg pretrained=false --hub-size 64 48"``: the run is repeated by giving them again
    beside its ``--descriptor hub:DIR[:ENTRY]``.
    """
    flags = hub_flags(options)
    return {HUB_SETTING: shlex.join(flags)} if flags else {}


# ------------------------------------------------------------------ the repository


def _hubconf(repo: Path, descriptor: str) -> Path:
    if not repo.is_dir():
        raise VPRInputError(
            f"hub repository {repo} (of {descriptor}) is not a folder; give a torch.hub repository (a clone, or "
            "~/.cache/torch/hub/<owner>_<repo>_<branch>)"
        )
    path = repo / HUBCONF
    if not path.is_file():
        raise VPRInputError(
            f"hub repository {repo} (of {descriptor}) has no {HUBCONF}, so it is no torch.hub repository; give the "
            "folder that holds hubconf.py"
        )
    return path


def hubconf_entries(path: Path) -> dict[str, EntrySignature]:
    """The public top-level functions of ``hubconf.py`` and their signatures, from its syntax tree.

    Raises:
        VPRInputError: the file is unreadable or not valid Python.
    """
    try:
        tree = ast.parse(path.read_bytes(), filename=str(path))
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot read it ({exc})") from exc
    except (SyntaxError, ValueError) as exc:
        where = f" line {exc.lineno}" if getattr(exc, "lineno", None) else ""
        raise VPRInputError(f"{path}:{where} is not valid Python ({exc.msg if hasattr(exc, 'msg') else exc}); "
                            "fix the repository's hubconf.py") from exc
    entries: dict[str, EntrySignature] = {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            a = node.args
            positional = [*a.posonlyargs, *a.args]
            defaults = [None] * (len(positional) - len(a.defaults)) + [ast.unparse(d) for d in a.defaults]
            params = [(p.arg, d) for p, d in zip(positional, defaults) if p not in a.posonlyargs]
            params += [(p.arg, None if d is None else ast.unparse(d)) for p, d in zip(a.kwonlyargs, a.kw_defaults)]
            entries[node.name] = EntrySignature(tuple(params), a.kwarg is not None)
    return entries


def _check_arguments(spec_call: str, signature: EntrySignature, args: Mapping[str, HubValue]) -> None:
    if signature.var_keyword:
        return
    names = {name for name, _ in signature.params}
    unknown = sorted(set(args) - names)
    missing = [name for name, default in signature.params if default is None and name not in args]
    if unknown:
        raise VPRInputError(
            f"hub entry {spec_call} has no argument {', '.join(unknown)}: it takes {signature.describe()}; "
            "fix or drop that --hub-arg"
        )
    if missing:
        raise VPRInputError(
            f"hub entry {spec_call} needs {', '.join(missing)}: it takes {signature.describe()}; "
            f"add --hub-arg {missing[0]}=..."
        )


def git_commit(repo: Path) -> str | None:
    """The commit checked out in ``repo`` when it is a git checkout, read from ``.git`` (git is not run).

    Follows ``.git`` files (worktrees, submodules: ``gitdir: PATH``), symbolic ``HEAD``
    refs, loose refs then ``packed-refs`` (in the common folder of a worktree too).
    ``None`` when ``repo`` is no checkout or the commit cannot be read.
    """
    git = repo / ".git"
    try:
        if git.is_file():
            text = git.read_text(encoding="utf-8").strip()
            if not text.startswith("gitdir:"):
                return None
            git = (repo / text[len("gitdir:"):].strip()).resolve()
        head = (git / "HEAD").read_text(encoding="utf-8").strip()
        if not head.startswith("ref:"):
            return head if _SHA.match(head) else None
        ref = head[len("ref:"):].strip()
        if not ref.startswith("refs/") or ".." in Path(ref).parts:
            return None
        roots = [git]
        if (git / "commondir").is_file():
            roots.append((git / (git / "commondir").read_text(encoding="utf-8").strip()).resolve())
        for root in roots:
            loose = root / ref
            if loose.is_file():
                sha = loose.read_text(encoding="utf-8").strip()
                return sha if _SHA.match(sha) else None
            packed = root / "packed-refs"
            if packed.is_file():
                for line in packed.read_text(encoding="utf-8").splitlines():
                    sha, _, name = line.partition(" ")
                    if name.strip() == ref and _SHA.match(sha):
                        return sha
    except (OSError, UnicodeDecodeError):
        return None
    return None


def source_digest(repo: Path) -> str:
    """sha256 over every ``.py`` file under ``repo`` (relative path and bytes, in path order).

    Hidden folders (``.git``...) and ``__pycache__`` are left out; folder links are not followed.

    Raises:
        VPRInputError: a file that cannot be read.
    """
    files = []
    for folder, subfolders, names in os.walk(repo):
        subfolders[:] = [d for d in subfolders if not d.startswith(".") and d != "__pycache__"]
        files += [Path(folder, n) for n in names if n.endswith(".py")]
    digest = hashlib.sha256()
    for path in sorted(files, key=lambda p: p.relative_to(repo).as_posix()):
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise VPRInputError(f"{path}: cannot read this file of the hub repository ({exc})") from exc
        digest.update(f"{path.relative_to(repo).as_posix()}\0{len(data)}\0".encode())
        digest.update(data)
    return digest.hexdigest()


def repo_identity(repo: Path) -> str:
    """``git:<commit>|py:<sha256>``, or ``py:<sha256>`` outside a git checkout (see :func:`source_digest`)."""
    commit = git_commit(repo)
    sources = f"py:{source_digest(repo)}"
    return f"git:{commit}|{sources}" if commit else sources


# ------------------------------------------------------------------ the model's description


def _side(value: object, what: str) -> int:
    low, high = INPUT_SIDE_RANGE
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise VPRInputError(f"{what}={value!r}: must be a whole number of pixels from {low} to {high}")
    return int(value)


def _nearest(side: int, patch: int) -> int:
    return max(patch, round(side / patch) * patch)


def check_patch(call: str, input_size: tuple[int, int] | None, short_side: int | None,
                patch: tuple[int, int]) -> None:
    """Refuse an input whose sides are not multiples of the ViT patch ``(patch_h, patch_w)``.

    Raises:
        VPRInputError: naming the model, the size, the nearest multiples and the option to give.
    """
    ph, pw = patch
    if input_size is None:
        raise VPRInputError(
            f"hub model {call} is a ViT with patch {ph}: short_side={short_side} leaves the long side free, so it may "
            f"not be a multiple of {ph}; give --hub-size W H (input_size) with multiples of {ph}, e.g. 322 322"
        )
    width, height = input_size
    if width % pw or height % ph:
        raise VPRInputError(
            f"hub model {call} is a ViT with patch {ph}: input size {width} x {height} is not a multiple of it; give "
            f"--hub-size {_nearest(width, pw)} {_nearest(height, ph)} (input_size)"
        )


def hub_model(
    descriptor: str,
    *,
    hub_args: object = None,
    input_size: int | Sequence[int] | None = None,
    short_side: int | None = None,
    normalisation: str | None = None,
) -> HubModel:
    """Validate ``hub:DIR[:ENTRY]`` and its options (nothing of the repository runs).

    Args:
        descriptor: ``hub:DIR`` or ``hub:DIR:ENTRY``.
        hub_args: the entry's keyword arguments (:func:`hub_arguments`).
        input_size: ``(width, height)`` or one number for a square; or
        short_side: the shorter side, aspect kept. Neither: :data:`KNOWN_MODELS`' input.
        normalisation: ``imagenet`` (default, or the table's), ``unit`` or ``signed``.

    Raises:
        VPRInputError: no such folder or ``hubconf.py``, no entry named and not exactly
            one defined, an argument the entry does not take or one it needs missing, a
            bad size or normalisation, a ViT size that is not a multiple of its patch.
    """
    repo, entry, entries = _resolve_entry(descriptor)
    args = hub_arguments(hub_args)
    shown = ", ".join(f"{k}={v!r}" for k, v in args)
    call = f"{entry}({shown}) of {repo}"
    if entry in entries:
        _check_arguments(call, entries[entry], dict(args))
    if input_size is not None and short_side is not None:
        raise VPRInputError(
            f"hub model {call}: give input_size (--hub-size) or short_side (--hub-short-side), not both"
        )
    known = next((k for k in KNOWN_MODELS if k.applies(repo.name, entry, dict(args))), None)
    if input_size is not None:
        square = isinstance(input_size, int) and not isinstance(input_size, bool)
        sides = (input_size, input_size) if square else input_size
        if isinstance(sides, (str, bytes)) or not isinstance(sides, Sequence) or len(sides) != 2:
            raise VPRInputError(f"input_size={input_size!r}: give one number (a square) or (width, height)")
        size: tuple[int, int] | None = (_side(sides[0], "input_size width"), _side(sides[1], "input_size height"))
        short = None
    elif short_side is not None:
        size, short = None, _side(short_side, "short_side")
    elif known is not None:
        size, short = known.input_size, known.short_side
    else:
        names = ", ".join(sorted({k.repository for k in KNOWN_MODELS}))
        raise VPRInputError(
            f"hub model {call} is not one of the known models ({names}): give its input, "
            "--hub-size W H (input_size) or --hub-short-side N (short_side), and "
            "--hub-normalisation if it is not imagenet"
        )
    if normalisation is None:
        how = known.normalisation if known is not None else Normalisation.IMAGENET
    else:
        try:
            how = Normalisation(normalisation)
        except ValueError:
            raise VPRInputError(
                f"normalisation={normalisation!r}: choose one of {', '.join(n.value for n in Normalisation)}"
            ) from None
    patch = known.patch if known is not None else None
    if patch is not None:
        check_patch(call, size, short, (patch, patch))
    return HubModel(repo=repo, entry=entry, args=args, input_size=size, short_side=short, normalisation=how,
                    patch=patch)


def _resolve_entry(descriptor: str) -> tuple[Path, str, dict[str, EntrySignature]]:
    """``(DIR, ENTRY, hubconf's entries)``: ENTRY named, else the one public function defined."""
    repo, entry = split_hub_name(descriptor)
    path = _hubconf(repo, descriptor)
    entries = hubconf_entries(path)
    if entry is None:
        if len(entries) != 1:
            listed = ", ".join(entries) or "none"
            raise VPRInputError(
                f"descriptor {descriptor!r}: {path} defines {len(entries)} public entries ({listed}); name one: "
                f"hub:{repo}:ENTRY"
            )
        (entry,) = entries
    return repo, entry, entries


def cache_name(descriptor: str) -> str:
    """``hub.<folder>.<entry>``: the name of ``descriptor``'s extractor, which its cache keys begin with.

    Reads ``hubconf.py``'s syntax tree when no entry is named; runs nothing.

    Raises:
        VPRInputError: as :func:`hub_model` for the folder and entry.
    """
    repo, entry, _entries = _resolve_entry(descriptor)
    return _extractor_name(repo, entry)


def model_digest(spec: HubModel, identity: str) -> str:
    """sha256 over the repository's identity, the entry, its typed arguments, the resize and normalisation."""
    args = json.dumps([[k, type(v).__name__, v] for k, v in spec.args])
    text = f"{identity}|{spec.entry}|{args}|{spec.resize}|{spec.normalisation.value}"
    return hashlib.sha256(text.encode()).hexdigest()


def unavailable_reason(descriptor: str, **_options: object) -> str | None:
    """``None`` when torch is installed and ``DIR`` holds a ``hubconf.py``, else why not (nothing runs)."""
    import importlib.util

    if importlib.util.find_spec("torch") is None:
        return "torch is not installed: pip install torch"
    try:
        repo, _entry = split_hub_name(descriptor)
        _hubconf(repo, descriptor)
    except VPRInputError as exc:
        return str(exc)
    return None


# ------------------------------------------------------------------ building


def _failed_in(exc: BaseException, path: Path, function: str) -> bool:
    """Whether ``exc`` was raised inside ``function`` of the file ``path`` (or below it)."""
    tb = exc.__traceback__
    while tb is not None:
        code = tb.tb_frame.f_code
        if code.co_name == function and Path(code.co_filename).resolve() == path:
            return True
        tb = tb.tb_next
    return False


def _offline_hint(exc: BaseException) -> str:
    from urllib.error import URLError

    seen, stack = set(), [exc]
    while stack:
        e = stack.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, (URLError, ConnectionError, TimeoutError)):
            return ("; it downloads something (weights, another hub repository): fill the torch hub cache on a "
                    "networked machine and copy $TORCH_HOME/hub here")
        stack += [e.__cause__, e.__context__]
    return ""


def _load(spec: HubModel, device):
    """``torch.hub.load(DIR, ENTRY, source="local", **args)``, on ``device`` in eval mode when a module."""
    import torch

    from vpr_explorer.descriptors.runtime import prepare

    path = spec.repo / HUBCONF
    try:
        model = torch.hub.load(str(spec.repo), spec.entry, source="local", verbose=False, **dict(spec.args))
    # The repository's code may raise anything while importing or building; it is bad input
    # naming the repository and entry rather than a crash of the app.
    except Exception as exc:
        said = f"{type(exc).__name__}: {str(exc)[:200]}"
        if isinstance(exc, RuntimeError) and str(exc).startswith("Cannot find callable"):
            entries = ", ".join(hubconf_entries(path)) or "none"
            raise VPRInputError(
                f"hub repository {spec.repo}: {HUBCONF} has no entry {spec.entry!r} (its public functions: {entries}); "
                f"name one as hub:{spec.repo}:ENTRY"
            ) from exc
        if isinstance(exc, RuntimeError) and str(exc).startswith("Missing dependencies"):
            raise VPRInputError(f"hub repository {spec.repo}: {str(exc)[:200]} (its {HUBCONF}'s dependencies); "
                                "pip install them") from exc
        if _failed_in(exc, path, spec.entry):
            raise VPRInputError(
                f"hub entry {spec.call} failed ({said}){_offline_hint(exc)}; check its --hub-arg values"
            ) from exc
        if isinstance(exc, TypeError) and not _failed_in(exc, path, "<module>"):
            # Raised by the call itself, before the entry's first line: the arguments do not fit.
            raise VPRInputError(
                f"hub entry {spec.call} refused its arguments ({said}); fix the --hub-arg values"
            ) from exc
        raise VPRInputError(
            f"hub repository {spec.repo}: importing its {HUBCONF} failed ({said}){_offline_hint(exc)}; fix it, or "
            "install what it imports"
        ) from exc
    if isinstance(model, torch.nn.Module):
        model = prepare(model, device, channels_last=False)
    elif not callable(model):
        raise VPRInputError(
            f"hub entry {spec.call} returned {type(model).__name__}, not a model; it must return a module mapping a "
            "(B, 3, H, W) batch to (B, D)"
        )
    return model


def model_patch(model: object) -> tuple[int, int] | None:
    """``(patch_h, patch_w)`` of the first submodule with a ``patch_size`` (a ViT's), else ``None``."""
    modules = getattr(model, "modules", None)
    if not callable(modules):
        return None
    for module in modules():
        patch = getattr(module, "patch_size", None)
        if isinstance(patch, int) and not isinstance(patch, bool) and patch > 1:
            return patch, patch
        if (isinstance(patch, (tuple, list)) and len(patch) == 2
                and all(isinstance(p, int) and not isinstance(p, bool) and p >= 1 for p in patch) and max(patch) > 1):
            return int(patch[0]), int(patch[1])
    return None


class _FirstOutput:
    """The model, its output's first element when it returns a tuple or list (BoQ: ``(descriptor, attentions)``)."""

    def __init__(self, model) -> None:
        self.model = model

    def __call__(self, x):
        y = self.model(x)
        return y[0] if isinstance(y, (tuple, list)) and y else y


def _build(spec: HubModel, identity: str, device, precision) -> Extractor:
    from vpr_explorer.descriptors.runtime import TorchExtractor, probe_length

    model = _load(spec, device)
    patch = model_patch(model)
    if patch is not None and spec.patch is None:
        check_patch(spec.call, spec.input_size, spec.short_side, patch)
    recipe = DeviceRecipe(normalisation=spec.normalisation, size=spec.input_size, short_side=spec.short_side)
    if spec.input_size is not None:
        width, height = spec.input_size
    else:
        width = height = spec.short_side
    extractor = TorchExtractor(
        name=spec.name,
        version=f"{RECIPE_VERSION}.{spec.resize}.{spec.normalisation.value}.{model_digest(spec, identity)[:12]}",
        dim=0,
        model=_FirstOutput(model),
        load=recipe.load,
        recipe=recipe,
        # A repository's model may view() its input: NCHW-contiguous is the safe layout.
        channels_last=False,
        device=device,
        precision=precision,
    )
    extractor.dim = probe_length(
        extractor, width, height, who=f"hub model {spec.call}",
        fix="check the input size (--hub-size / --hub-short-side) and the model",
        returns="it must return (B, D) descriptors (or a tuple whose first element is): pick the entry that returns "
                "the descriptor model")
    return extractor


def build_extractor(
    descriptor: str,
    *,
    hub_args: object = None,
    input_size: int | Sequence[int] | None = None,
    short_side: int | None = None,
    normalisation: str | None = None,
    device: str = "auto",
    precision: str = "fp32",
) -> Extractor:
    """The extractor of ``hub:DIR[:ENTRY]`` (shared per repository state, options, device and precision).

    Args: as :func:`hub_model`, and ``device`` / ``precision`` as every torch extractor
    (:func:`~vpr_explorer.descriptors.runtime.resolve_device`, ``resolve_precision``).

    Raises:
        VPRInputError: what :func:`hub_model` refuses; the hubconf failing on import, a
            missing entry or dependency, the entry failing or refusing its arguments, a
            forward pass that fails or returns no ``(B, D)``, a ViT size not a multiple of
            its patch; each naming the repository and entry.
    """
    from vpr_explorer.descriptors.runtime import resolve_device, resolve_precision, shared

    spec = hub_model(descriptor, hub_args=hub_args, input_size=input_size, short_side=short_side,
                     normalisation=normalisation)
    resolved = resolve_device(device)
    mode = resolve_precision(precision, resolved)
    identity = repo_identity(spec.repo)
    key = ("hub", spec, identity, str(resolved), mode)
    return shared(key, lambda: _build(spec, identity, resolved, mode))
