"""A user's own model as an extractor: a TorchScript or torch.export file, or a Python entry point.

A model is registered by name, in code (``register_extractor``) or in a settings file
named by ``VPR_EXPLORER_MODELS`` (TOML, one table per model)::

    [models.my-net]
    model = "nets/my_net.pt"           # TorchScript (torch.jit.save), relative to this file
    # model = "nets/my_net.pt2"        # or a torch.export program (torch.export.save)
    # model = "my_package.nets:build"  # or an entry point: module:function
    # model = "nets/build.py:build"    # or a function in a .py file
    input_size = [320, 240]            # width, height; or one number for a square
    normalisation = "imagenet"         # or "unit" ([0, 1]) or "signed" ([-1, 1])
    dim = 512                          # optional: checked against the model's output
    version = "v2"                     # optional: bump it when weights the model loads change

A torch.hub model (:mod:`~vpr_explorer.descriptors.hub`) is named the same way, once, so that
every command and the app's descriptor list offer it by that name::

    [models.megaloc]
    model = "hub:~/.cache/torch/hub/gmberton_MegaLoc_main:get_trained_model"  # hub:DIR[:ENTRY]
    # hub_args = { backbone_name = "dinov2", output_dim = 12288 }  # the entry's keyword arguments
    # input_size = [322, 322]        # or short_side = 480; default: the known model's input
    # normalisation = "imagenet"     # default: the known model's, else imagenet

``get_extractor("megaloc")`` is then ``get_extractor("hub:DIR:ENTRY", hub_args=..., input_size=...,
short_side=..., normalisation=...)`` with the fields given: the same extractor, name and cache
key as ``--descriptor hub:DIR:ENTRY`` with the same ``--hub-*`` flags, so each finds what the
other cached. A relative ``DIR`` is read from the settings file's folder, ``~`` is the home
folder; ``dim`` and ``version`` do not apply (the key holds the repository's code). The hub
table's values are checked when the file is read; the repository only when the model is built
(:func:`~vpr_explorer.descriptors.hub.hub_model`). The settings file is the operator's: naming
a repository there is the choice to run its code, which no link or typed path of the app can make.

The model receives a ``(B, 3, H, W)`` float32 batch on the extractor's device: RGB,
resized bilinearly (aspect not kept) to ``input_size``, normalised as named
(``imagenet``: ``(x / 255 - mean) / std`` with torchvision's ImageNet statistics). It
returns ``(B, D)`` descriptors; the pipeline L2-normalises them. An entry point is called
with no arguments and returns that callable (an ``nn.Module`` is put in eval mode on the
device; a plain function gets the batch as is). An exported program needs a dynamic
batch dimension (``dynamic_shapes={"x": {0: torch.export.Dim("batch", min=1)}}``).

The cache key holds the sha256 of the model's file (the TorchScript file, or the entry
point's source file) with the input size, normalisation and ``version``, so an edited
model never reuses stale descriptors. An entry point's key sees only its own source
file: weights it reads from elsewhere are covered by ``version``.

This module imports no torch until a model is built, so listing models stays cheap.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

from vpr_explorer.descriptors.base import Extractor
from vpr_explorer.descriptors.hub import PREFIX as HUB_PREFIX, hub_arguments, split_hub_name
from vpr_explorer.descriptors.preprocess import INPUT_SIDE_RANGE, RECIPE_VERSION, DeviceRecipe, Normalisation
from vpr_explorer.errors import VPRInputError

MODELS_ENV = "VPR_EXPLORER_MODELS"
EXPORTED_SUFFIX = ".pt2"  # torch.export.save's; any other file is read as TorchScript
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
_VERSION = re.compile(r"^[A-Za-z0-9._-]{0,32}$")
_ENTRY_POINT = re.compile(r"^(?P<module>[A-Za-z_][\w.]*|.+\.py):(?P<function>[A-Za-z_]\w*)$")
_SETTINGS_FIELDS = ("model", "input_size", "normalisation", "dim", "version")
_HUB_FIELDS = ("model", "hub_args", "input_size", "short_side", "normalisation")


@dataclass(frozen=True)
class CustomModel:
    """A registered user model; made by :func:`custom_model`, which validates it.

    Attributes:
        name: registry name (letters, digits, ``. _ -``), also the cache key's prefix.
        source: what the user gave: a TorchScript path or ``module:function``.
        file: the TorchScript file or the entry point's ``.py`` file (``None`` for an
            entry point named by module, found at build time).
        module, function: the entry point, when it is one.
        input_size: ``(width, height)`` fed to the model.
        normalisation: pixel normalisation.
        dim: expected descriptor length, or ``None`` to take the model's.
        version: the user's tag, part of the cache key.
    """

    name: str
    source: str
    file: Path | None
    module: str | None
    function: str | None
    input_size: tuple[int, int]
    normalisation: Normalisation
    dim: int | None
    version: str

    @property
    def is_entry_point(self) -> bool:
        return self.function is not None


@dataclass(frozen=True)
class HubSetting:
    """A torch.hub model named in the settings file; made by :func:`hub_setting`, which validates it.

    Attributes:
        name: its name in the settings file (letters, digits, ``. _ -``).
        descriptor: ``hub:DIR[:ENTRY]``, ``DIR`` absolute.
        options: ``(option, value)`` pairs of ``get_extractor(descriptor, ...)``, sorted: ``hub_args``
            (sorted ``(key, value)`` pairs), ``input_size`` (``(width, height)``), ``short_side``,
            ``normalisation``, those given.
    """

    name: str
    descriptor: str
    options: tuple[tuple[str, object], ...]


def _input_size(value: object, where: str) -> tuple[int, int]:
    low, high = INPUT_SIDE_RANGE
    sides = (value, value) if isinstance(value, int) and not isinstance(value, bool) else value
    if (
        not isinstance(sides, (tuple, list))
        or len(sides) != 2
        or not all(isinstance(s, int) and not isinstance(s, bool) and low <= s <= high for s in sides)
    ):
        raise VPRInputError(
            f"{where}input_size={value!r}: give one number (a square) or [width, height], whole pixels "
            f"from {low} to {high}"
        )
    return int(sides[0]), int(sides[1])


def custom_model(
    name: str,
    model: str | os.PathLike[str],
    *,
    input_size: int | tuple[int, int] = 224,
    normalisation: str = "imagenet",
    dim: int | None = None,
    version: str = "",
    base: Path | None = None,
    where: str = "",
) -> CustomModel:
    """Validate a registration; relative paths are resolved against ``base`` (else the cwd).

    Raises:
        VPRInputError: naming the parameter (prefixed by ``where``, e.g. the settings
            file) and the fix.
    """
    if not isinstance(name, str) or not _NAME.match(name):
        raise VPRInputError(
            f"{where}name={name!r}: use 1-64 letters, digits and . _ - (it becomes the cache folder's name)"
        )
    if not isinstance(model, (str, os.PathLike)) or not str(model).strip():
        raise VPRInputError(f"{where}model={model!r}: give a TorchScript file or an entry point module:function")
    if isinstance(model, str) and model.strip().startswith(HUB_PREFIX):
        raise VPRInputError(f"{where}model={model!r}: a torch.hub model is get_extractor({model.strip()!r}, ...) "
                            f"itself, or a table of the {MODELS_ENV} settings file")
    source = str(model).strip()
    base = base if base is not None else Path.cwd()
    entry = _ENTRY_POINT.match(source) if isinstance(model, str) else None
    file = module = function = None
    if entry is not None:
        function = entry["function"]
        if entry["module"].endswith(".py"):
            file = (base / Path(entry["module"]).expanduser()).resolve()
        else:
            module = entry["module"]
    else:
        file = (base / Path(source).expanduser()).resolve()
    try:
        how = Normalisation(normalisation)
    except ValueError:
        raise VPRInputError(
            f"{where}normalisation={normalisation!r}: choose one of {', '.join(n.value for n in Normalisation)}"
        ) from None
    if dim is not None and (isinstance(dim, bool) or not isinstance(dim, int) or dim < 1):
        raise VPRInputError(f"{where}dim={dim!r}: must be a whole number >= 1, or left out")
    if not isinstance(version, str) or not _VERSION.match(version):
        raise VPRInputError(f"{where}version={version!r}: use up to 32 letters, digits and . _ -")
    return CustomModel(
        name=name,
        source=source,
        file=file,
        module=module,
        function=function,
        input_size=_input_size(input_size, where),
        normalisation=how,
        dim=dim,
        version=version,
    )


def unavailable_reason(spec: CustomModel) -> str | None:
    """``None`` when the model's file or module is there, else why not (cheap: nothing is imported)."""
    if importlib.util.find_spec("torch") is None:
        return "torch is not installed: pip install torch"
    if spec.file is not None and not spec.file.is_file():
        kind = "entry point file" if spec.is_entry_point else "model file"
        return f"{spec.file}: the {kind} of model {spec.name!r} does not exist; fix the path it was registered with"
    if spec.module is not None and importlib.util.find_spec(spec.module.split(".")[0]) is None:
        return f"module {spec.module!r} of model {spec.name!r} cannot be found; install it or fix the entry point"
    return None


# ------------------------------------------------------------------ settings file


def hub_setting(name: str, table: dict, *, base: Path, where: str = "") -> HubSetting:
    """A settings file's table whose ``model`` is ``hub:DIR[:ENTRY]`` (format in the module docstring).

    Nothing of the repository is read: its folder, ``hubconf.py`` and entry are checked when
    the model is built.

    Raises:
        VPRInputError: a bad name, an unknown field, ``hub_args`` that is not a table of
            None/bool/number/string values, a bad ``input_size``, ``short_side`` or
            ``normalisation``, or both ``input_size`` and ``short_side``; prefixed by ``where``.
    """
    if not isinstance(name, str) or not _NAME.match(name):
        raise VPRInputError(
            f"{where}name={name!r}: use 1-64 letters, digits and . _ - (the descriptor's name in every command)"
        )
    extra = sorted(set(table) - set(_HUB_FIELDS))
    if extra:
        raise VPRInputError(f"{where}has field(s) {', '.join(extra)} that a hub: model does not take: use "
                            f"{', '.join(_HUB_FIELDS)}")
    rest = table["model"].strip()[len(HUB_PREFIX):]
    if rest and not rest.startswith("~") and not Path(rest).is_absolute():
        rest = str(base / rest)
    try:
        folder, entry = split_hub_name(HUB_PREFIX + rest)
    except VPRInputError as exc:
        raise VPRInputError(f"{where}{exc}") from None
    options: dict[str, object] = {}
    if "hub_args" in table:
        if not isinstance(table["hub_args"], dict):
            raise VPRInputError(f"{where}hub_args={table['hub_args']!r}: give a table, e.g. "
                                "hub_args = { backbone_name = \"dinov2\" }")
        try:
            options["hub_args"] = hub_arguments(table["hub_args"])
        except VPRInputError as exc:
            raise VPRInputError(f"{where}{exc}") from None
    if "input_size" in table and "short_side" in table:
        raise VPRInputError(f"{where}gives input_size and short_side: give one of them")
    if "input_size" in table:
        options["input_size"] = _input_size(table["input_size"], where)
    if "short_side" in table:
        low, high = INPUT_SIDE_RANGE
        side = table["short_side"]
        if isinstance(side, bool) or not isinstance(side, int) or not low <= side <= high:
            raise VPRInputError(f"{where}short_side={side!r}: must be a whole number of pixels from {low} to {high}")
        options["short_side"] = side
    if "normalisation" in table:
        try:
            options["normalisation"] = Normalisation(table["normalisation"]).value
        except ValueError:
            raise VPRInputError(f"{where}normalisation={table['normalisation']!r}: choose one of "
                                f"{', '.join(n.value for n in Normalisation)}") from None
    descriptor = HUB_PREFIX + str(folder) + (f":{entry}" if entry else "")
    return HubSetting(name=name, descriptor=descriptor, options=tuple(sorted(options.items())))


def read_settings(path: Path) -> dict[str, CustomModel | HubSetting]:
    """The models of a settings file (format in the module docstring).

    Raises:
        VPRInputError: naming the file and the entry at fault.
    """
    try:
        with open(path, "rb") as fh:
            settings = tomllib.load(fh)
    except FileNotFoundError as exc:
        raise VPRInputError(f"{MODELS_ENV}={path}: no such file; fix or unset the variable") from exc
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise VPRInputError(f"{path}: cannot read it as TOML ({exc}); fix the models file") from exc
    models = settings.get("models", {})
    unknown = sorted(set(settings) - {"models"})
    if unknown or not isinstance(models, dict):
        raise VPRInputError(f"{path}: expected only [models.<name>] tables, found {', '.join(unknown) or 'models'}")
    out: dict[str, CustomModel] = {}
    for name, table in models.items():
        where = f"{path}: [models.{name}] "
        if not isinstance(table, dict):
            raise VPRInputError(f"{where}must be a table with model = ...")
        if isinstance(table.get("model"), str) and table["model"].strip().startswith(HUB_PREFIX):
            out[name] = hub_setting(name, table, base=path.parent, where=where)
            continue
        extra = sorted(set(table) - set(_SETTINGS_FIELDS))
        if extra:
            raise VPRInputError(f"{where}has unknown field(s) {', '.join(extra)}: use {', '.join(_SETTINGS_FIELDS)}")
        if "model" not in table:
            raise VPRInputError(f"{where}has no model = (a TorchScript file or module:function)")
        out[name] = custom_model(name, **table, base=path.parent, where=where)
    return out


def settings_models() -> dict[str, CustomModel | HubSetting]:
    """The models of the ``VPR_EXPLORER_MODELS`` file; none when the variable is unset."""
    value = os.environ.get(MODELS_ENV)
    return read_settings(Path(value).expanduser()) if value else {}


# ------------------------------------------------------------------ building


def _source_file(spec: CustomModel) -> Path | None:
    """The file whose bytes identify the model."""
    if spec.file is not None:
        return spec.file
    try:
        found = importlib.util.find_spec(spec.module)
    except (ImportError, ValueError) as exc:
        raise VPRInputError(f"model {spec.name!r}: cannot find module {spec.module!r} ({exc}); install it") from exc
    if found is None:
        raise VPRInputError(f"model {spec.name!r}: cannot find module {spec.module!r}; install it or fix the entry point")
    return Path(found.origin) if found.origin and os.path.isfile(found.origin) else None


def model_digest(spec: CustomModel) -> str:
    """sha256 over the model file's bytes, the input size, normalisation and version tag."""
    digest = hashlib.sha256()
    source = _source_file(spec)
    if source is not None:
        try:
            with open(source, "rb") as fh:
                digest.update(hashlib.file_digest(fh, "sha256").digest())
        except OSError as exc:
            raise VPRInputError(f"{source}: cannot read the model file of {spec.name!r} ({exc})") from exc
    else:
        digest.update(spec.source.encode())
    width, height = spec.input_size
    digest.update(f"|{width}x{height}|{spec.normalisation.value}|{spec.version}".encode())
    return digest.hexdigest()


def _load_callable(spec: CustomModel, device):
    """The user's callable, on ``device`` when it is a module."""
    import torch

    if spec.file is not None and spec.file.suffix == EXPORTED_SUFFIX:
        import torch.export.passes

        try:
            program = torch.export.load(str(spec.file))
        except (RuntimeError, ValueError, OSError, KeyError) as exc:
            raise VPRInputError(
                f"{spec.file}: cannot load it as a torch.export program ({str(exc)[:200]}); save the model with "
                "torch.export.save(torch.export.export(model, (example,)), path)"
            ) from exc
        # An exported module cannot be switched to eval mode: it was traced in the mode it
        # was exported in.
        return torch.export.passes.move_to_device_pass(program, device).module()
    if not spec.is_entry_point:
        try:
            return torch.jit.load(str(spec.file), map_location=device).eval()
        except (RuntimeError, ValueError, OSError) as exc:
            raise VPRInputError(
                f"{spec.file}: cannot load it as TorchScript ({str(exc)[:200]}); save the model with "
                "torch.jit.save(torch.jit.script(model), path), or as a torch.export program (.pt2), or register "
                "an entry point module:function"
            ) from exc
    try:
        if spec.file is not None:
            loader = importlib.util.spec_from_file_location("vpr_explorer_user_model_" + re.sub(r"\W", "_", spec.name), spec.file)
            module = importlib.util.module_from_spec(loader)
            loader.loader.exec_module(module)
        else:
            module = importlib.import_module(spec.module)
        factory = getattr(module, spec.function)
        model = factory()
    # The user's code may raise anything while importing or building; it is reported as
    # bad input naming the entry point rather than surfacing as a crash of the app.
    except Exception as exc:
        raise VPRInputError(
            f"model {spec.name!r}: the entry point {spec.source} failed ({type(exc).__name__}: {str(exc)[:200]}); "
            "fix it so that calling it returns the model"
        ) from exc
    if not callable(model):
        raise VPRInputError(
            f"model {spec.name!r}: {spec.source} returned {type(model).__name__}, not a callable; "
            "return a module or function mapping a (B, 3, H, W) batch to (B, D)"
        )
    if isinstance(model, torch.nn.Module):
        from vpr_explorer.descriptors.runtime import prepare

        model = prepare(model, device, channels_last=False)
    return model


def _build(spec: CustomModel, device, precision) -> Extractor:
    from vpr_explorer.descriptors.runtime import TorchExtractor, probe_length

    model = _load_callable(spec, device)
    recipe = DeviceRecipe(normalisation=spec.normalisation, size=spec.input_size)
    width, height = spec.input_size
    extractor = TorchExtractor(
        name=spec.name,
        version=f"{RECIPE_VERSION}.{width}x{height}.{spec.normalisation.value}.{model_digest(spec)[:12]}",
        dim=spec.dim or 0,
        model=model,
        load=recipe.load,
        recipe=recipe,
        # Users' models may view() their input: NCHW-contiguous is the safe layout.
        channels_last=False,
        device=device,
        precision=precision,
    )
    dim = probe_length(extractor, width, height, who=f"model {spec.name!r}:", fix="check input_size and the model",
                       returns="it must return (B, D) descriptors")
    if spec.dim is not None and dim != spec.dim:
        raise VPRInputError(
            f"model {spec.name!r}: returns {dim}-d descriptors, registered as dim={spec.dim}; fix dim or leave it out"
        )
    extractor.dim = dim
    return extractor


def build_extractor(spec: CustomModel, device: str = "auto", precision: str = "fp32") -> Extractor:
    """The extractor of a registered model (shared per model file, device and precision).

    Raises:
        VPRInputError: the file is missing or not TorchScript, the entry point fails or
            returns no callable, or the output is not ``(B, D)`` (of ``dim``).
    """
    from vpr_explorer.descriptors.runtime import file_identity, resolve_device, resolve_precision, shared

    reason = unavailable_reason(spec)
    if reason is not None:
        raise VPRInputError(f"descriptor {spec.name!r} is unavailable here: {reason}")
    resolved = resolve_device(device)
    mode = resolve_precision(precision, resolved)
    source = _source_file(spec)
    identity = file_identity(source) if source is not None else None
    key = ("custom", spec, identity, str(resolved), mode)
    return shared(key, lambda: _build(spec, resolved, mode))
