"""Running a torch model as an extractor: device, precision, checkpoints, shared models.

Shared by the paper's models (AlexNet conv3, CosPlace, EigenPlaces) and users' own
models. What makes extraction fast lives here: ``torch.inference_mode``, channels-last
activations, the GPU when there is one (``device="auto"``), batches copied to it from
pinned memory without blocking, and optional bf16/fp16 autocast.

Precision is part of an extractor's cache key: ``fp32`` descriptors are the same on CPU
and GPU up to float rounding (TF32 is switched off for fp32 convolutions on the GPU for
that reason), so they share one key; ``bf16`` / ``fp16`` ones differ by ~1e-2 and get
keys of their own (``+bf16``, ``+fp16``), so they are never mixed.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import pickle
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from vpr_explorer.descriptors.base import Extractor
from vpr_explorer.errors import VPRInputError

if TYPE_CHECKING:
    from vpr_explorer.descriptors.preprocess import DeviceRecipe

# Models kept alive per process (each is 50-250 MB, AlexNet's projection 1 GB more).
MAX_SHARED_MODELS = 4
NAMED_KEYS = 3


class Precision(StrEnum):
    """Arithmetic of the forward pass."""

    FP32 = "fp32"
    BF16 = "bf16"
    FP16 = "fp16"


_AUTOCAST_DTYPE = {Precision.BF16: torch.bfloat16, Precision.FP16: torch.float16}
_VERSION_SUFFIX = {Precision.FP32: "", Precision.BF16: "+bf16", Precision.FP16: "+fp16"}


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """``"auto"`` -> the GPU when torch sees one, else the CPU; other names are checked.

    Raises:
        VPRInputError: for a device that is not ``auto``, ``cpu``, ``cuda`` or
            ``cuda:N``, or a GPU torch cannot see.
    """
    if device is None or device == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        resolved = None
    if resolved is None or resolved.type not in ("cpu", "cuda"):
        raise VPRInputError(f"device={device!r}: choose 'auto', 'cpu', 'cuda' or 'cuda:N'")
    if resolved.type == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise VPRInputError(f"device={device!r}: torch sees no CUDA GPU here; use device='cpu' or 'auto'")
    index = torch.cuda.current_device() if resolved.index is None else resolved.index
    if index >= torch.cuda.device_count():
        raise VPRInputError(f"device={device!r}: there are {torch.cuda.device_count()} GPU(s); choose cuda:0 upwards")
    return torch.device("cuda", index)


def resolve_precision(precision: str, device: torch.device) -> Precision:
    """The precision named, checked against the device.

    Raises:
        VPRInputError: for an unknown name, or fp16 on the CPU (slow or unsupported there).
    """
    try:
        resolved = Precision(precision)
    except ValueError:
        raise VPRInputError(
            f"precision={precision!r}: choose one of {', '.join(p.value for p in Precision)}"
        ) from None
    if resolved is Precision.FP16 and device.type != "cuda":
        raise VPRInputError("precision='fp16' needs a GPU; use 'bf16' or 'fp32' on the CPU")
    return resolved


# ------------------------------------------------------------------ checkpoints


def file_identity(path: Path) -> tuple[str, int, int]:
    """``(resolved path, size, mtime_ns)``: changes whenever the file is replaced or edited."""
    stat = path.stat()
    return str(path.resolve()), stat.st_size, stat.st_mtime_ns


def read_checkpoint(path: Path, what: str) -> tuple[dict[str, torch.Tensor], str]:
    """A state dict from a ``.pth`` file and the sha256 of the file's bytes.

    Accepts a plain state dict (what the official repositories publish) or a training
    checkpoint holding one under ``model_state_dict`` / ``state_dict``. Loaded with
    ``weights_only=True``: a checkpoint cannot run code.

    Raises:
        VPRInputError: naming ``path`` when it is unreadable or holds no state dict.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot read the weights file ({exc}); check the path and its permissions") from exc
    digest = hashlib.sha256(data).hexdigest()
    try:
        loaded = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, KeyError, AttributeError, ImportError) as exc:
        raise VPRInputError(
            f"{path}: cannot read it as a PyTorch checkpoint ({type(exc).__name__}: {str(exc)[:200]}); "
            f"expected {what}: download it again"
        ) from exc
    if isinstance(loaded, Mapping):
        for key in ("model_state_dict", "state_dict"):
            if isinstance(loaded.get(key), Mapping):
                loaded = loaded[key]
                break
    if not isinstance(loaded, Mapping) or not loaded or not all(isinstance(v, torch.Tensor) for v in loaded.values()):
        raise VPRInputError(f"{path}: holds no state dict of tensors; expected {what}")
    return dict(loaded), digest


def load_strict(model: torch.nn.Module, state: Mapping[str, torch.Tensor], path: Path, what: str, fix: str) -> None:
    """``model.load_state_dict(state, strict=True)``, with an error that says what is off.

    Raises:
        VPRInputError: naming ``path``, the first missing / unexpected keys and shape
            mismatches, and ``fix``.
    """
    expected = model.state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    mismatched = [
        f"{k} is {tuple(state[k].shape)} where {tuple(expected[k].shape)} is expected"
        for k in expected
        if k in state and state[k].shape != expected[k].shape
    ]
    problems = []
    for label, items in (("missing keys", missing), ("unexpected keys", unexpected), ("wrong shapes", mismatched)):
        if items:
            more = f" and {len(items) - NAMED_KEYS} more" if len(items) > NAMED_KEYS else ""
            problems.append(f"{label}: {', '.join(items[:NAMED_KEYS])}{more}")
    if problems:
        raise VPRInputError(f"{path}: is not a {what} checkpoint ({'; '.join(problems)}); {fix}")
    model.load_state_dict(state, strict=True)


# ------------------------------------------------------------------ sharing


_SHARED: OrderedDict[tuple, Extractor] = OrderedDict()
_SHARED_LOCK = threading.Lock()


def shared(key: tuple, build: Callable[[], Extractor]) -> Extractor:
    """The extractor built for ``key`` in this process, built on first use.

    Two first callers (two Streamlit sessions) wait for one build instead of both
    spending seconds on it; the least recently used model goes beyond
    ``MAX_SHARED_MODELS``.
    """
    with _SHARED_LOCK:
        if key in _SHARED:
            _SHARED.move_to_end(key)
            return _SHARED[key]
        extractor = build()
        _SHARED[key] = extractor
        while len(_SHARED) > MAX_SHARED_MODELS:
            _SHARED.popitem(last=False)
        return extractor


# ------------------------------------------------------------------ running


def prepare(model: torch.nn.Module, device: torch.device, channels_last: bool) -> torch.nn.Module:
    """Eval mode, no gradients, on ``device``, channels-last weights when asked."""
    model = model.eval().to(device)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    for p in model.parameters():
        p.requires_grad_(False)
    return model


class TorchExtractor(Extractor):
    """An extractor whose descriptor is a torch callable's output.

    Args:
        name, version, dim: as :class:`Extractor`; the precision's suffix is appended
            to ``version``.
        model: ``(B, C, H, W)`` float tensor on ``device`` -> ``(B, dim)`` tensor.
        load: ``path -> (C, H, W)`` float32 array (runs in the decoding threads).
        device: where ``model`` lives (:func:`resolve_device`).
        precision: fp32, or bf16/fp16 autocast.
        channels_last: feed NHWC-strided batches (faster convolutions on CPU and GPU).
        recipe: ``load``'s rule in tensor terms, for decoding JPEGs on ``device``
            (:mod:`~vpr_explorer.descriptors.device_decode`); ``None``: images are
            loaded on the CPU only.
    """

    def __init__(
        self,
        *,
        name: str,
        version: str,
        dim: int,
        model: Callable[[torch.Tensor], torch.Tensor],
        load: Callable[[Path], np.ndarray],
        device: torch.device,
        precision: Precision = Precision.FP32,
        channels_last: bool = True,
        recipe: DeviceRecipe | None = None,
    ) -> None:
        self.name = name
        self.version = version + _VERSION_SUFFIX[precision]
        self.dim = dim
        self.device = device
        self.precision = precision
        self._model = model
        self._load = load
        self._channels_last = channels_last
        self.recipe = recipe

    def load(self, path: Path) -> np.ndarray:
        return self._load(path)

    def _context(self) -> contextlib.ExitStack:
        stack = contextlib.ExitStack()
        stack.enter_context(torch.inference_mode())
        if self.precision is not Precision.FP32:
            stack.enter_context(torch.autocast(self.device.type, dtype=_AUTOCAST_DTYPE[self.precision]))
        if self.device.type == "cuda":
            # benchmark: fixed input shapes, so cuDNN's fastest algorithm is worth finding
            # once. TF32 off in fp32 keeps GPU descriptors equal to the CPU's (one cache key).
            stack.enter_context(
                torch.backends.cudnn.flags(
                    enabled=True, benchmark=True, deterministic=False, allow_tf32=self.precision is not Precision.FP32
                )
            )
        return stack

    def run(self, x: torch.Tensor) -> torch.Tensor:
        """The model on a batch tensor already on :attr:`device`; returns ``(B, dim)`` on it."""
        if self._channels_last and x.dim() == 4:
            x = x.contiguous(memory_format=torch.channels_last)
        with self._context():
            return self._model(x)

    def forward(self, batch: np.ndarray) -> np.ndarray:
        """``(B, C, H, W)`` float32 -> ``(B, dim)`` float32, computed on :attr:`device`."""
        x = torch.from_numpy(np.ascontiguousarray(batch, dtype=np.float32))
        if self.device.type == "cuda":
            # Pinned host memory lets the copy run by DMA while the CPU goes on.
            x = x.pin_memory().to(self.device, non_blocking=True)
        return self.forward_tensor(x)

    def forward_tensor(self, x: torch.Tensor) -> np.ndarray:
        """``(B, C, H, W)`` float32 already on :attr:`device` -> ``(B, dim)`` float32 on the CPU."""
        y = self.run(x)
        if not isinstance(y, torch.Tensor):
            raise VPRInputError(
                f"descriptor {self.name!r}: the model returned {type(y).__name__}, not a tensor; "
                "make it return a (B, D) tensor"
            )
        return y.detach().float().cpu().numpy()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(cache_key={self.cache_key!r}, dim={self.dim}, device={str(self.device)!r})"


def probe_length(extractor: TorchExtractor, width: int, height: int, *, who: str, fix: str, returns: str) -> int:
    """The descriptor length of a model from one black ``(1, 3, height, width)`` image, before any real work.

    Args:
        who: how messages name the model (``"model 'x':"``, ``"hub model DIR:ENTRY"``).
        fix: what to check when the forward pass fails.
        returns: what to do when the output is not ``(1, D)``.

    Raises:
        VPRInputError: the forward pass fails, its output is not ``(1, D)`` with D ≥ 1, or holds NaN or ±inf.
    """
    try:
        probe = extractor.forward(np.zeros((1, 3, height, width), dtype=np.float32))
    except VPRInputError:
        raise  # already says what is wrong
    except Exception as exc:  # the model's own forward pass: reported as bad input
        raise VPRInputError(f"{who} fails on a (1, 3, {height}, {width}) batch ({type(exc).__name__}: "
                            f"{str(exc)[:200]}); {fix}") from exc
    if probe.ndim != 2 or probe.shape[0] != 1 or probe.shape[1] < 1:
        raise VPRInputError(f"{who} maps a (1, 3, {height}, {width}) batch to shape {tuple(probe.shape)}; {returns}")
    if not np.isfinite(probe).all():
        raise VPRInputError(f"{who} returns NaN or infinite values on a black image; check the model")
    return int(probe.shape[1])
