"""The one error type the library raises for bad input, and the number check the method modules share."""

from __future__ import annotations

import math


class VPRInputError(ValueError):
    """Bad input: names the file or parameter at fault and what to do about it.

    The command line prints it as one line and exits 2; the app shows it with
    ``st.error``. Anything else that escapes the library is a bug.
    """


def finite_number(value: object, name: str) -> float:
    """``value`` as a finite ``float`` (a bool is not a number here), or a ``VPRInputError`` naming ``name``."""
    if isinstance(value, bool):
        raise VPRInputError(f"{name} must be a number, got {value!r}")
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise VPRInputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise VPRInputError(f"{name} must be finite, got {value!r}")
    return x
