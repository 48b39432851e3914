"""Reading ``.npy`` files without running anything stored in them.

``np.load`` unpickles an object array when it is allowed to, and a pickle can call any
Python function (``os.system`` included). Here an array of numbers is read with
``allow_pickle=False``; an object array (what ``np.save`` writes for VPR-Bench's
``ground_truth_new.npy``) is rebuilt by an unpickler that admits exactly the globals
numpy's own pickles name: ``_reconstruct`` (of an empty ``ndarray``), ``ndarray``,
``dtype`` (booleans, integers, floats, complex numbers and objects, no records) and
``scalar``, under ``numpy.core.multiarray`` (written by numpy < 2, Python 2 included) or
``numpy._core.multiarray``. Each of them is replaced by a stand-in that checks its
arguments and builds the array itself; any other global (``os.system``,
``builtins.eval``, ...) is refused before anything is called, and so is a file without
the ``.npy`` signature, which ``np.load`` would hand to ``pickle``.

What an object array holds is then only what a pickle builds without calling anything
(ints, floats, strings, lists, tuples, dicts, ...) and numpy arrays and scalars; a caller
checks it is what it expects, e.g. with :func:`as_indices`.
"""

from __future__ import annotations

import math
import pickle
import re
import tokenize
from pathlib import Path

import numpy as np
import numpy.lib.format as npy_format

from vpr_explorer.errors import VPRInputError

#: Modules numpy's pickles name the array builders under (numpy >= 2, and older numpy).
_MULTIARRAY = ("numpy._core.multiarray", "numpy.core.multiarray")
#: The dtype strings numpy pickles for plain numbers and objects ('i8', '<f8', 'O8', ...).
_DTYPE_SPEC = re.compile(r"[<>|=]?(?:b1|[iu][1248]|f(?:2|4|8|12|16)|c(?:8|16|24|32)|O[48]?)")
#: Nesting deeper than this is no table of indices (and a pickle can make a list hold itself).
MAX_DEPTH = 8
_NOT_RUN = "nothing in the file was run"


class _Refused(Exception):
    """A pickle asks for something the restricted unpickler does not build."""


class _Builder:
    """A stand-in for one admitted numpy global: a callable without attributes.

    Having neither ``__dict__`` nor ``__setstate__``, a stand-in cannot be altered by a
    pickle's ``BUILD``; it is shared by every load.
    """

    __slots__ = ()


class _ArrayType(_Builder):
    """``numpy.ndarray``: only ever the first argument of ``_reconstruct``."""

    __slots__ = ()

    def __call__(self, *args, **kwargs):
        raise _Refused("a direct call of numpy.ndarray")


class _Dtype:
    """A dtype being unpickled: made by ``numpy.dtype(spec, align, copy)``, then given its state by ``BUILD``."""

    __slots__ = ("dtype",)

    def __init__(self, dtype: np.dtype) -> None:
        self.dtype = dtype

    def __setstate__(self, state) -> None:
        # numpy writes (3, byte order, subarray, names, fields, elsize, alignment, flags); a
        # subarray, field names or fields would make a record, which is not read.
        if not (isinstance(state, tuple) and len(state) == 8 and state[0] in (3, 4)
                and state[1] in ("<", ">", "|", "=") and state[2:5] == (None, None, None)):
            raise _Refused(f"a dtype of state {str(state)[:80]} (only plain numbers and objects are read)")
        if state[1] in ("<", ">") and self.dtype.itemsize > 1 and self.dtype.kind != "O":
            self.dtype = self.dtype.newbyteorder(state[1])


class _DtypeType(_Builder):
    """``numpy.dtype``: booleans, integers, floats, complex numbers and objects only."""

    __slots__ = ()

    def __call__(self, spec=None, align=False, copy=True) -> _Dtype:
        if not isinstance(spec, str) or not _DTYPE_SPEC.fullmatch(spec) or align not in (False, 0):
            raise _Refused(f"numpy.dtype({str(spec)[:40]!r}) (only plain numbers and objects are read)")
        return _Dtype(np.dtype(spec))


def _data_bytes(data, what: str) -> bytes:
    # Python 2 pickles hold raw bytes as str, decoded here as latin-1 (as np.load's encoding="latin1")
    if isinstance(data, str):
        return data.encode("latin-1")
    if isinstance(data, bytes | bytearray):
        return bytes(data)
    raise _Refused(f"{what} whose data is {type(data).__name__}")


class _Array:
    """An array being unpickled: made by ``_reconstruct(ndarray, (0,), b"b")``, then given its state by ``BUILD``."""

    __slots__ = ("array",)

    def __init__(self) -> None:
        self.array: np.ndarray | None = None

    def __setstate__(self, state) -> None:
        # numpy writes (version 1, shape, dtype, Fortran order, data): bytes, or a list for objects
        if not (isinstance(state, tuple) and len(state) == 5 and state[0] == 1):
            raise _Refused(f"an array state of {type(state).__name__} {str(state)[:80]}")
        _, shape, dtype, fortran, data = state
        if (not isinstance(shape, tuple) or not all(type(s) is int and s >= 0 for s in shape)
                or not isinstance(dtype, _Dtype) or fortran not in (True, False, 0, 1)):
            raise _Refused(f"an array of shape {str(shape)[:40]} and dtype {str(dtype)[:40]}")
        dt, n, order = dtype.dtype, math.prod(shape), "F" if fortran else "C"
        if dt.kind == "O":
            if not isinstance(data, list) or len(data) != n:
                raise _Refused(f"an object array of shape {shape} whose data is not a list of {n} items")
            flat = np.empty(n, dtype=object)
            for i, item in enumerate(data):
                flat[i] = item
        else:
            raw = _data_bytes(data, "an array")
            if len(raw) != n * dt.itemsize:
                raise _Refused(f"an array of shape {shape} {dt} with {len(raw)} bytes of data "
                               f"instead of {n * dt.itemsize}")
            flat = np.frombuffer(raw, dtype=dt)
        self.array = flat.reshape(shape, order=order)


class _Reconstruct(_Builder):
    """``numpy.core.multiarray._reconstruct``: an empty array that ``BUILD`` fills."""

    __slots__ = ()

    def __call__(self, subtype=None, shape=None, typecode=None) -> _Array:
        if subtype is not _NDARRAY or shape != (0,) or typecode not in (b"b", "b"):
            raise _Refused(f"_reconstruct({str(subtype)[:40]}, {str(shape)[:40]}, {str(typecode)[:20]})")
        return _Array()


class _Scalar(_Builder):
    """``numpy.core.multiarray.scalar``: one number, returned as a Python number."""

    __slots__ = ()

    def __call__(self, dtype=None, data=None):
        if not isinstance(dtype, _Dtype):
            raise _Refused(f"scalar({str(dtype)[:40]}, ...)")
        if dtype.dtype.kind == "O":
            return data
        raw = _data_bytes(data, "a scalar")
        if len(raw) != dtype.dtype.itemsize:
            raise _Refused(f"a {dtype.dtype} scalar of {len(raw)} bytes")
        return np.frombuffer(raw, dtype=dtype.dtype)[0].item()


_NDARRAY = _ArrayType()
_ADMITTED: dict[tuple[str, str], _Builder] = {
    **{(m, "_reconstruct"): _Reconstruct() for m in _MULTIARRAY},
    **{(m, "scalar"): _Scalar() for m in _MULTIARRAY},
    ("numpy", "ndarray"): _NDARRAY,
    ("numpy", "dtype"): _DtypeType(),
}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Admits numpy's array, dtype and scalar builders (as checked stand-ins) and nothing else."""

    def find_class(self, module: str, name: str):
        try:
            return _ADMITTED[(module, name)]
        except KeyError:
            raise _Refused(f"{module}.{name}") from None

    def persistent_load(self, pid):
        raise _Refused(f"a persistent id {str(pid)[:40]}")


def _resolve(value, depth: int = 0):
    """``value`` with the unpickling stand-ins replaced by the arrays they built."""
    if depth > MAX_DEPTH:
        raise _Refused(f"data nested more than {MAX_DEPTH} levels deep")
    if isinstance(value, _Array):
        if value.array is None:
            raise _Refused("an array without its data")
        value = value.array
    if isinstance(value, np.ndarray) and value.dtype == object:
        out = np.empty(value.shape, dtype=object)
        for index, item in np.ndenumerate(value):
            out[index] = _resolve(item, depth + 1)
        return out
    if isinstance(value, list | tuple):
        return type(value)(_resolve(item, depth + 1) for item in value)
    if isinstance(value, _Dtype | _Builder):
        raise _Refused("a bare numpy dtype or builder where a value belongs")
    return value


def _unreadable(path: Path, why: object) -> VPRInputError:
    return VPRInputError(f"{path}: cannot read it as a NumPy .npy file ({why}); {_NOT_RUN}")


def _header(fh, path: Path) -> tuple[tuple[int, ...], bool, np.dtype]:
    """``(shape, fortran_order, dtype)`` from the header, with ``fh`` left at the data."""
    head = fh.read(len(npy_format.MAGIC_PREFIX))
    fh.seek(0)
    if head != npy_format.MAGIC_PREFIX:
        if npy_format.MAGIC_PREFIX.startswith(head):
            raise _unreadable(path, f"truncated: {len(head)} bytes")
        pickled = " (it looks like a bare Python pickle, which is never loaded)" if head[:1] == b"\x80" else ""
        raise VPRInputError(f"{path}: not a NumPy .npy file: it does not start with the .npy signature "
                            f"\\x93NUMPY{pickled}; {_NOT_RUN}")
    try:
        version = npy_format.read_magic(fh)
        if version == (1, 0):
            return npy_format.read_array_header_1_0(fh)
        if version == (2, 0):
            return npy_format.read_array_header_2_0(fh)
    except (ValueError, SyntaxError, tokenize.TokenError, EOFError) as exc:
        # numpy parsing a damaged or truncated header
        raise _unreadable(path, f"damaged or truncated header: {str(exc)[:160]}") from None
    raise _unreadable(path, f".npy format version {version[0]}.{version[1]}, not 1.0 or 2.0")


def read_npy(path: Path) -> np.ndarray:
    """The array in a ``.npy`` file, read without running anything the file holds.

    Numbers (booleans, integers, floats, complex, records of them) are read with
    ``allow_pickle=False``; an object array through the restricted unpickler (module
    docstring). Its nested arrays come back as plain ``np.ndarray``, its numpy scalars as
    Python numbers; its items are unchecked (:func:`as_indices` checks indices).

    Raises:
        VPRInputError: naming ``path``: not a ``.npy`` file (a bare pickle included),
            truncated, or an object array whose pickle asks for anything but numpy's array
            builders.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            shape, _, dtype = _header(fh, path)
            if not dtype.hasobject:
                size, start = path.stat().st_size, fh.tell()
                need = math.prod(shape) * dtype.itemsize
                if need > size - start:
                    raise VPRInputError(f"{path}: truncated: its header promises an array of {dtype}, shape {shape} "
                                        f"({need:,} bytes), but {size - start:,} bytes follow it")
                fh.seek(0)
                try:
                    return npy_format.read_array(fh, allow_pickle=False)
                except ValueError as exc:
                    raise _unreadable(path, str(exc)[:160]) from None
            if dtype != np.dtype(object):
                raise _unreadable(path, f"a record dtype holding objects, {dtype}")
            try:
                loaded = _resolve(_NumpyOnlyUnpickler(fh, encoding="latin1").load())
            except _Refused as exc:
                raise VPRInputError(f"{path}: refused: its pickled data asks for {exc}, and only numpy arrays "
                                    f"of numbers are read from a .npy file; {_NOT_RUN}") from None
            except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError,
                    OverflowError, RecursionError) as exc:
                raise _unreadable(path, f"its pickled data is damaged or truncated: {type(exc).__name__}: "
                                        f"{str(exc)[:120]}") from None
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot read it ({exc.strerror or exc}); check the path and its "
                            "permissions") from None
    if not isinstance(loaded, np.ndarray) or loaded.dtype != object or loaded.shape != shape:
        got = (f"an object array of shape {loaded.shape}" if isinstance(loaded, np.ndarray)
               else type(loaded).__name__)
        raise _unreadable(path, f"its header promises an object array of shape {shape}, its data is {got}")
    return loaded


# --------------------------------------------------------------------------- indices

_KIND_NAMES = {bool: "a bool", float: "a float", complex: "a complex number", str: "text", bytes: "bytes",
               type(None): "None", dict: "a dict", list: "a list", tuple: "a tuple", set: "a set"}
_INT64 = np.iinfo(np.int64)


def _kind(value) -> str:
    if isinstance(value, np.ndarray):
        return f"an array of {value.dtype}"
    if isinstance(value, np.generic):
        return f"a {value.dtype}"
    return _KIND_NAMES.get(type(value), f"a {type(value).__name__}")


def _shown(value) -> str:
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, dict | set | np.ndarray):
        return ""
    text = repr(value)
    return f" {text if len(text) <= 40 else text[:37] + '...'}"


def _is_integer(value) -> bool:
    return (isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)
            and _INT64.min <= int(value) <= _INT64.max)


def as_indices(value, *, path: Path, where: str, what: str = "index") -> np.ndarray:
    """``(k,)`` int64 indices from an int, a list or tuple of ints, or an array of integers.

    ``where`` and ``what`` place the value in the file for the message (``"row 3"``,
    ``"reference"``). Nothing is rounded or cast: a float (``0.9``, ``2.0``, NaN), a
    complex number, a bool, text, None or a nested list is refused as it was found.

    Raises:
        VPRInputError: naming ``path``, ``where`` and the first value that is not an
            integer (or not one of int64's).
    """

    def refuse(bad) -> VPRInputError:
        if isinstance(bad, int | np.integer) and not isinstance(bad, bool | np.bool_):
            return VPRInputError(f"{path}: {where}: {what} {int(bad)} is outside any image's index")
        return VPRInputError(f"{path}: {where}: {what}{_shown(bad)} is {_kind(bad)}; indices must be integers")

    if isinstance(value, np.ndarray):
        flat = value.reshape(-1)
        if flat.dtype.kind in "iu":
            if flat.size and flat.dtype.kind == "u" and flat.max() > _INT64.max:
                raise refuse(flat[flat > _INT64.max][0])
            return flat.astype(np.int64)
        if flat.dtype.kind != "O":
            if flat.size == 0 and flat.dtype.kind in "bfc":
                return np.empty(0, dtype=np.int64)  # np.array([]) is float64: no references
            # name a value that is not whole (0.9, NaN) before one that merely has the wrong type (2.0)
            fractional = (np.flatnonzero(~np.isfinite(flat) | (flat != np.round(flat)))
                          if flat.dtype.kind in "fc" else ())
            raise refuse(flat[fractional[0] if len(fractional) else 0] if flat.size else flat)
        value = list(flat)
    if isinstance(value, list | tuple):
        for item in value:
            if not _is_integer(item):
                raise refuse(item)
        return np.array([int(v) for v in value], dtype=np.int64)
    if _is_integer(value):
        return np.array([int(value)], dtype=np.int64)
    raise refuse(value)
