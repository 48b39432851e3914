"""Playback: a dataset's queries decided one by one, in their order, watched in rerun's web viewer.

One body for every layout: the dataset value in use (aligned traversals: the query
traversal's frames against every other traversal) with its places, recorded by
``recording.record_playback``. Any query of the recording opens in the Query inspector
(same query, k and places), where each method's decision is explained and drawn. A checkbox
adds the acceptance bench (every acceptance rule on the same value and places, ``cache.bench``)
to the recording: each rule's decision of every query on the same timeline.

The viewer is ``ui.rerun_viewer``'s component, and it and the query box below move together
on the ``query`` timeline of this recording. Where the viewer's time cursor stands (played,
dragged, or set in the viewer), the box stands too, with its caption and button: the cursor
is the view's frame. A number the user puts in the box (typed, or by its steppers) is the
view's frame and a seek: the viewer shows this recording, its cursor paused at that query
(``rerun_viewer.request_seek``). The page redrawn with the cursor's own positions, while the
viewer plays or is dragged, seeks nothing. Where that component cannot run (rerun-notebook
missing), rerun's own web viewer is shown in an iframe, with the reason, and neither follows
the other.
"""

import numpy as np
import streamlit as st

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.database import Verdict
from vpr_explorer.method.places import BETWEEN_PLACES_RULE
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.protocols.acceptance import REFERENCE_SHARE, BenchOptions
from vpr_explorer.recording import (
    BENCH_SETS,
    RECORDED,
    TIMELINE,
    bench_lines,
    record_playback,
    verdicts,
    viewer_servers,
)
from vpr_explorer.views.numbers import UNKNOWN, query_label

from vpr_explorer.app.ui import cache, rerun_viewer, state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import PLACES_HINT, progress_reporter, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed, page_file
from vpr_explorer.app.ui.state import K_RANGE

ensure_routed(__file__)

VIEWER_HEIGHT = 860
VIEWER_KEY = "w_playback_viewer"

st.title("Playback")
st.caption(
    "Play the queries back against the database, one by one in their order, in rerun's viewer: what the camera saw, "
    "the database image behind each answer, the place answered (or the rejection) and whether it was right, "
    "and how close the decision was (raw_p, θ_p and the margin of the best place). The paper's method (margin "
    "rule, weighted θ) and the place-level baseline run side by side; thresholds come from the database only."
)
with stop_on_input_error():
    cur = current()
ds = cur.dataset
v = state.view()
noun = "frame" if ds.query_frame is not None else "query"  # aligned traversals: query q is frame q

cols = st.columns([3, 2])
cols[0].markdown(f"**Queries:** the {ds.n_queries:,} images of {cur.query}, in order; **database:** "
                 f"{', '.join(cur.database)} ({ds.n_database:,} images); **places:** {cur.places.describe(cur.dataset)}. "
                 "The query traversal and the places are set on the **Places** page.")
k = cols[1].slider("k: θ_p(k) = θ_p + k·s_p (k = 0 is the paper)", K_RANGE[0], K_RANGE[1], step=0.25,
                   help="θ_p(k) = θ_p + k·s_p, where s_p is the standard deviation of the place's negative mixture "
                        "(its database images' scores against other places): k = 0 is the paper's threshold, and "
                        "raising k moves every place's threshold up, rejecting more queries.",
                   **state.bind("w_playback_k", "k", float(min(max(v.k, K_RANGE[0]), K_RANGE[1]))))
with_bench = cols[1].checkbox(
    "include the acceptance bench", key="w_playback_bench",
    help="Also runs every acceptance rule of the acceptance bench (image-level top-1, per-place θ_p and θ_k, "
         "per-query threshold, graph matcher, SeqSLAM, top-1 distance, PA-ratio, SUE) on the same queries, database "
         f"and places, on the whole database (closed set) and on its first {REFERENCE_SHARE:.0%} (natural open set), "
         "and records each rule's confidence, acceptance (1 or 0) and decision of every query on the same "
         f"`{TIMELINE}` timeline, under {' and '.join(f'{root}/<rule>' for root, _ in BENCH_SETS.values())}. "
         "A rule that cannot run here (e.g. the sequence rules against several database traversals) is left out, "
         "and the recording's bench summary says why.")

if st.button("Record and play", type="primary", icon=":material/play_circle:",
             help="Decides every query against the database under the paper's method and the place-level "
                  "baseline, writes the decisions, scores and images to a rerun recording (.rrd) and shows it in the "
                  "viewer below."):
    with stop_on_input_error(hint=PLACES_HINT):
        fitted = cache.fitted(cur.data, cur.places)
    report = None
    if with_bench:
        with stop_on_input_error(hint="Record without the acceptance bench, or choose fewer queries or a smaller "
                                      "database."):
            report = cache.bench(cur.data, cur.places, BenchOptions())
    progress, clear = progress_reporter(f"Recording {ds.n_queries} queries of {cur.query}")
    try:
        with stop_on_input_error(hint="Change k above, or the places on the **Places** page."):
            st.session_state["playback"] = record_playback(fitted, cur.data.descriptors, serve=True, k=k,
                                                           descriptor=cur.data.descriptor, progress=progress,
                                                           bench=report)
    finally:
        clear()

playback = st.session_state.get("playback")
if playback is None:
    st.stop()

st.subheader(f"{playback.dataset}: {playback.query} against {', '.join(playback.database)}")
rows = ["| method | right | wrong accepts | wrong rejects | between places (not scored) |", "|---|---|---|---|---|"]
for key, c in playback.counts().items():
    rows.append(f"| {METHODS_BY_KEY[key].label} | {c[Verdict.RIGHT]} | {c[Verdict.WRONG_ACCEPT]} | "
                f"{c[Verdict.WRONG_REJECT]} | {c[Verdict.BETWEEN]} |")
st.markdown("\n".join(rows))
if playback.bench is not None:
    told = "; ".join(line.strip() for line in bench_lines(playback.bench))
    st.caption(f"Acceptance bench recorded with it: {told}. Its summaries, decision logs and series (confidence, "
               "accepted) are tabs of the viewer's lower right panel.")
unknown = int((playback.decisions.status == UNKNOWN).sum())
st.caption(
    f"Recording `{playback.recording_id}`, {playback.n_queries} queries on the `{TIMELINE}` timeline: press play in "
    "the viewer's time panel or drag its cursor. Methods: "
    f"{' and '.join(f'{short} = {METHODS_BY_KEY[key].label}' for key, short in RECORDED.items())}. "
    "Decision levels: INFO right, ERROR wrong accept, WARN wrong reject, DEBUG between places, not scored. "
    + (f"{unknown} queries have no right database image (an unknown place): rejecting them is right, accepting "
       "them a wrong accept. " if unknown else "")
    + f"{BETWEEN_PLACES_RULE} "
    "Route: the query's position in blue, answers green (right) or red (wrong), where the dataset has positions "
    "or frames. The viewer lists every recording made on this server (this one shown); pick another in its "
    f"recordings panel. The {noun} box below the viewer follows its time cursor on this recording, and a "
    f"{noun} put in the box moves the cursor there (paused)."
)


same = (playback.dataset, playback.query, playback.database, playback.n_queries) == (
    ds.name, cur.query, cur.database, ds.n_queries)
said = {key: verdicts(playback.decisions, key) for key in RECORDED}
wrong = [q for q, verdict in enumerate(said["margin-weighted"])
         if verdict in (Verdict.WRONG_ACCEPT.value, Verdict.WRONG_REJECT.value)]
default = v.frame if v.frame is not None and 0 <= v.frame < playback.n_queries else (wrong[0] if wrong else 0)


def follow(cursor: rerun_viewer.Cursor) -> None:
    """The viewer's cursor moved: its query becomes the view's frame (the box below is drawn from it)."""
    q = cursor.position(playback.recording_id, TIMELINE, playback.n_queries)
    if q is not None and same:
        state.update(frame=q)


try:
    rerun_viewer.viewer(viewer_servers().grpc_url, playback.recording_id, timeline=TIMELINE, height=VIEWER_HEIGHT,
                        key=VIEWER_KEY, sequence=int(default) if same else None, on_cursor=follow)
except VPRInputError as exc:
    st.caption(f"rerun's own web viewer below: the viewer that reports its time cursor cannot run ({exc}), so the "
               f"{noun} box does not follow the cursor, nor the cursor the box.")
    st.iframe(playback.viewer_url, height=VIEWER_HEIGHT)
st.download_button(
    "Download the .rrd", data=playback.rrd.read_bytes, icon=":material/download:", on_click="ignore",
    file_name=f"{playback.dataset}_{playback.query}_vs_{'+'.join(playback.database)}.rrd",
    mime="application/octet-stream", help="Open it later with `rerun FILE.rrd`.",
)

st.subheader(f"Open a {noun} in the Query inspector")
if not same:
    st.info(f"This recording is of {playback.dataset} ({playback.query} against {', '.join(playback.database)}); the "
            f"app now looks at {ds.name} ({cur.query} against {', '.join(cur.database)}): record again to open its "
            "queries in the Query inspector.", icon=":material/info:")
    st.stop()


def seek(frame: int | None) -> None:
    """The user's number, committed as the view's frame: the viewer's cursor goes there too."""
    if frame is not None:
        rerun_viewer.request_seek(VIEWER_KEY, frame)


pick, told, go = st.columns([1, 3, 2], vertical_alignment="bottom")
pick.number_input(
    noun, 0, playback.n_queries - 1, step=1, **state.bind("w_playback_frame", "frame", int(default), then=seek),
    help=f"A query of the recording by its number (0 to {playback.n_queries - 1}, in order: for aligned traversals "
         f"the query traversal's frame): the one the viewer's time cursor shows on its `{TIMELINE}` timeline. It "
         "follows the cursor as you drag or play it, and the cursor follows it: a number typed here (or stepped "
         "to) moves the cursor there, paused. The button opens it in the Query inspector. Queries the "
         "paper's method got wrong here: "
         f"{', '.join(map(str, wrong[:12])) or 'none'}{' …' if len(wrong) > 12 else ''}.",
)
q = int(np.clip(state.view().frame if state.view().frame is not None else default, 0, playback.n_queries - 1))
told.markdown(f"**{query_label(ds, q)}**: " + "; ".join(
    f"{short} ({METHODS_BY_KEY[key].label}): **{said[key][q]}**" for key, short in RECORDED.items()))
if go.button(f"Open {noun} {q} in the Query inspector", key="w_playback_inspect", icon=":material/search:",
             help="Shows this query in the Query inspector: its candidate places under every method, their "
                  "thresholds and margins, and each decision in words."):
    state.update(frame=q, **({"query": playback.query} if ds.aligned is not None else {}))  # the traversal named
    st.switch_page(page_file("inspector"))
