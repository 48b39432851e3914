"""The place widgets (geometry, group/step in frames or metres, reading) that never leave the user stuck.

``place_controls`` draws what the dataset offers: a geometry radio where there are several,
group/step sliders counting frames (aligned traversals) or database images in listed order,
or group/step boxes in metres; nothing but a note where the layout fixes the places.
The readings of step are told in the unit group/step count (``reading_label``): frames,
database images or metres. Every change is checked (``retrieval_places``) before it
replaces the view's.

In the stride reading places overlap when ``step < group``, so raising group above step is
refused (the view keeps its places). Refusing alone leaves the user to guess that step must
move first; ``refuse_overlap`` remembers the pair that would work (step moved along with
group) and ``offer_fix`` shows it as one button under the refusal.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import streamlit as st

from vpr_explorer.data.layouts import RetrievalDataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceGeometry, Reading, retrieval_places
from vpr_explorer.views.numbers import RetrievalPlaces, geometries, geometry_label

from vpr_explorer.app.ui import state
from vpr_explorer.app.ui.current import effective_places

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


def check(dataset: RetrievalDataset, places: RetrievalPlaces, **changes) -> None:
    """Make the places of ``dataset`` with ``places`` (the view's, defaults resolved) changed so.

    Raises:
        VPRInputError: they overlap, or leave fewer than 2 places.
    """
    pinned = ({} if places.spec is None else {"group": places.spec.group, "step": places.spec.step}) | (
        {} if places.metric is None else {"group_m": places.metric.group, "step_m": places.metric.step})
    p = effective_places(dataclasses.replace(state.view(), **{**pinned, **changes}), dataset)
    retrieval_places(dataset, p.spec, p.metric)


def frame_unit(dataset: RetrievalDataset) -> str:
    """What group/step count in frames geometry: the frames of aligned traversals, else database images."""
    return "frames" if dataset.n_frames else "database images"


def reading_label(reading: Reading, unit: str) -> str:
    """The reading of step in the unit group/step count (frames, database images or metres)."""
    if reading is Reading.STRIDE:
        return f"stride: a place starts every `step` {unit} (authors' code, paper's numbers)"
    return f"skip: take `group` {unit}, skip the next `step` (paper's text)"


def place_controls(dataset: RetrievalDataset, places: RetrievalPlaces) -> None:
    """Geometry, group/step (frames or metres) and reading, each checked before it replaces the view's."""
    ds = dataset
    offered = geometries(ds)
    if not offered:
        st.info(f"{ds.name!r}: places given by the layout (the {ds.layout.value} layout names the place of every "
                "database image): group/step do not apply.", icon=":material/info:")
        return
    if len(offered) > 1:
        st.radio("places from", [g.value for g in offered], format_func=lambda g: geometry_label(PlaceGeometry(g)),
                 help="Frames: group/step count the frames of every traversal (aligned traversals), or the database "
                      "images in listed order (what `vpr-explorer list` prints). Route: metres along the route. "
                      "Lattice: square cells over the plane (unordered data such as Pittsburgh, SF-XL).",
                 **state.bind("w_geometry", "geometry", places.geometry.value,
                              validate=lambda g: check(ds, places, geometry=g)))
    c1, c2, c3 = st.columns([2, 2, 3])
    unit = frame_unit(ds) if places.spec is not None else "metres"
    if places.spec is not None:
        spec, n, what = places.spec, ds.n_frames or ds.n_database, frame_unit(ds)

        def check_group(g) -> None:
            refuse_overlap(lambda: check(ds, places, group=g), group_field="group", step_field="step", group=g,
                           step=spec.step, stride=spec.reading is Reading.STRIDE)

        offer_fix(lambda g: check(ds, places, group=g, step=g))
        c1.slider(f"group: {what} per place", 1, group_slider_top(spec.group, n),
                  **state.bind("w_group", "group", spec.group, validate=check_group))
        c2.slider(f"step: {what} from one place to the next", 1, step_slider_top(spec.step, n),
                  **state.bind("w_step", "step", spec.step, validate=lambda x: check(ds, places, step=x)))
        reading = spec.reading
    else:
        metric = places.metric

        def check_group_m(g) -> None:
            refuse_overlap(lambda: check(ds, places, group_m=g), group_field="group_m", step_field="step_m", group=g,
                           step=metric.step, stride=metric.reading is Reading.STRIDE, unit=" m")

        offer_fix(lambda g: check(ds, places, group_m=g, step_m=g))
        c1.number_input("group (m): metres per place", *GROUP_M_RANGE, step=5.0, format="%g",
                        **state.bind("w_group_m", "group_m", float(metric.group), validate=check_group_m))
        c2.number_input("step (m): metres from one place to the next", *STEP_M_RANGE, step=5.0, format="%g",
                        **state.bind("w_step_m", "step_m", float(metric.step),
                                     validate=lambda x: check(ds, places, step_m=x)))
        reading = metric.reading
    c3.radio("reading of step", [r.value for r in Reading], format_func=lambda r: reading_label(Reading(r), unit),
             **state.bind("w_reading", "reading", reading.value, validate=lambda r: check(ds, places, reading=r)))
