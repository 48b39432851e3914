"""The one error type the library raises for bad input."""

from __future__ import annotations


class VPRInputError(ValueError):
    """Bad input: names the file or parameter at fault and what to do about it.

    The command line prints it as one line and exits 2; the app shows it with
    ``st.error``. Anything else that escapes the library is a bug.
    """
