"""How the app reports bad input and long work: ``st.error`` (never a traceback), ``st.progress``.

The library raises one error type, ``VPRInputError``, whose message names the file or
parameter and the fix; here it becomes an ``st.error``. Anything else escaping a page is
a bug and Streamlit's own exception box is the right way to see it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import streamlit as st

from vpr_explorer.errors import VPRInputError

DATASET_HINT = "Fix it on the **Dataset** page, or pick another dataset there."
PLACES_HINT = "Change group or step on the **Places** page."


class FixOn(VPRInputError):
    """A library input error that knows where the app fixes it (``hint``, naming the page)."""

    def __init__(self, exc: VPRInputError, hint: str) -> None:
        super().__init__(str(exc))
        self.hint = hint


@contextmanager
def fixed_on(hint: str) -> Iterator[None]:
    """Attach ``hint`` (where the input at fault is set) to a ``VPRInputError`` raised inside."""
    try:
        yield
    except FixOn:
        raise
    except VPRInputError as exc:
        raise FixOn(exc, hint) from exc


def show_error(exc: VPRInputError, *, hint: str | None = None) -> None:
    """Show a library input error, with a hint of where to fix it."""
    st.error(f"{exc}" + (f"\n\n{hint}" if hint else ""), icon=":material/error:")


@contextmanager
def stop_on_input_error(hint: str | None = None) -> Iterator[None]:
    """Run a page's work; on ``VPRInputError`` show it and stop the page (the sidebar stays usable).

    The hint is the error's own (``FixOn``) where it has one, else ``hint``: it names the
    page whose control sets the input at fault.
    """
    try:
        yield
    except VPRInputError as exc:
        show_error(exc, hint=getattr(exc, "hint", None) or hint)
        st.stop()


def show_rejected() -> None:
    """Show (once) the error of an input a widget callback refused, e.g. a group/step leaving one place."""
    message = st.session_state.pop("rejected_input", None)
    if message:
        st.error(f"{message}\n\nThe previous value is kept.", icon=":material/error:")


def progress_reporter(label: str) -> tuple[Callable[..., None], Callable[[], None]]:
    """A ``progress(done, total, *msg)`` callback drawing ``st.progress`` with a time estimate, and a ``clear``.

    The estimate extrapolates the rate so far: remaining ≈ elapsed / done × (total − done).
    """
    bar = st.empty()
    start = time.perf_counter()

    def update(done: int, total: int, *message: object) -> None:
        frac = min(1.0, done / total) if total else 1.0
        elapsed = time.perf_counter() - start
        eta = f", about {elapsed / done * (total - done):.0f} s left" if 0 < done < total else ""
        extra = f" ({message[0]})" if message and message[0] else ""
        bar.progress(frac, text=f"{label}: {done}/{total}{extra}, {elapsed:.0f} s{eta}")

    def clear() -> None:
        bar.empty()

    return update, clear
