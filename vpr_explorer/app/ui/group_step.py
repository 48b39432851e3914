"""Group/step widgets that never leave the user stuck: a group raised above step is offered a way out.

In the stride reading places overlap when ``step < group``, so raising group above step is
refused (the view keeps its places). Refusing alone leaves the user to guess that step must
move first; ``refuse_overlap`` remembers the pair that would work (step moved along with
group) and ``offer_fix`` shows it as one button under the refusal.
"""

from __future__ import annotations

from collections.abc import Callable

import streamlit as st

from vpr_explorer.errors import VPRInputError

from vpr_explorer.app.ui import state

_FIX = "group_step_fix"

GROUP_SLIDER_TOP = 20
"""The group slider's top in frames or database images (:func:`group_slider_top`)."""
STEP_SLIDER_TOP = 60
"""The step slider's top in frames or database images (:func:`step_slider_top`)."""
GROUP_M_RANGE = (0.5, 100_000.0)
"""The group box's range in metres."""
STEP_M_RANGE = (0.5, 1_000_000.0)
"""The step box's range in metres."""


def group_slider_top(group: int, n: int) -> int:
    """The group slider's top over ``n`` frames or database images.

    Returns:
        ``GROUP_SLIDER_TOP``, or half of ``n`` when that is less; never below the view's
        ``group`` (a link may ask for more) or 2.
    """
    return max(2, group, min(GROUP_SLIDER_TOP, n // 2))


def step_slider_top(step: int, n: int) -> int:
    """The step slider's top over ``n`` frames or database images.

    Returns:
        ``STEP_SLIDER_TOP``, or ``n - 1`` when that is less; never below the view's ``step``
        or 2.
    """
    return max(2, step, min(STEP_SLIDER_TOP, n - 1))


def refuse_overlap(check: Callable[[], None], *, group_field: str, step_field: str, group: float, step: float,
                   stride: bool, unit: str = "") -> None:
    """Run ``check`` (group/step validation); when a group above step is refused in the stride
    reading, remember the pair with step moved along, for ``offer_fix``, and re-raise."""
    try:
        check()
    except VPRInputError:
        if stride and group > step:
            st.session_state[_FIX] = (group_field, step_field, group, unit)
        raise


def offer_fix(validate: Callable[[float], None]) -> None:
    """Under a refused group, a button that sets step to the same value as group (places then touch).

    ``validate(group)`` checks the pair ``(group, group)`` before it is committed.
    """
    fix = st.session_state.pop(_FIX, None)
    if fix is None:
        return
    group_field, step_field, group, unit = fix

    def apply() -> None:
        state.commit(**{group_field: group, step_field: group}, validate=lambda: validate(group))

    st.button(f"Move step along: group {group:g}{unit}, step {group:g}{unit}", key="w_fix_overlap", on_click=apply,
              icon=":material/swap_horiz:",
              help="In the stride reading a place starts every `step`: step must be at least group. This sets both.")
