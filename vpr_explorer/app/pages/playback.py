"""Playback: a query traversal decided frame by frame, watched in rerun's web viewer."""

import streamlit as st

from vpr_explorer.recording import RECORDED, Verdict, record_playback
from vpr_explorer.retrieval import METHODS_BY_KEY

from vpr_explorer.app.ui import state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import progress_reporter, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed
from vpr_explorer.app.ui.state import K_RANGE

ensure_routed(__file__)

VIEWER_HEIGHT = 860

st.title("Playback")
st.caption(
    "Play a query traversal back against the database, frame by frame, in rerun's viewer: what the camera saw, "
    "the database image behind each answer, the place answered (or the rejection) and whether it was right, "
    "and how close the decision was (raw_p, θ_p and the margin of the best place). The paper's method (margin "
    "rule, weighted θ) and the place-level baseline run side by side; thresholds come from the database only."
)
with stop_on_input_error():
    cur = current()
ds = cur.data.dataset
v = state.view()

cols = st.columns([2, 3, 2])
query = cols[0].selectbox("Query traversal", list(ds.traversals), **state.bind("w_query", "query", cur.query))
others = [t for t in ds.traversals if t != query]
database = cols[1].multiselect(
    "Database traversals", others, default=[t for t in cur.database if t in others] or others,
    key=f"w_playback_database_{query}", help="Thresholds θ_p are fitted on these traversals' images only.",
)
k = cols[2].slider("k: θ_p(k) = θ_p + k·s_p (k = 0 is the paper)", K_RANGE[0], K_RANGE[1], step=0.25,
                   **state.bind("w_playback_k", "k", float(min(max(v.k, K_RANGE[0]), K_RANGE[1]))))

if st.button("Record and play", type="primary", icon=":material/play_circle:", disabled=not database):
    progress, clear = progress_reporter(f"Recording {ds.n_frames} frames of {query}")
    try:
        with stop_on_input_error(hint="Change the traversals or k above, or group/step on the **Places** page."):
            st.session_state["playback"] = record_playback(
                ds, cur.data.descriptors, cur.spec, database=database, queries=query, serve=True, k=k,
                descriptor=cur.data.descriptor, progress=progress,
            )
    finally:
        clear()
if not database:
    st.info("Choose at least one database traversal.", icon=":material/info:")

playback = st.session_state.get("playback")
if playback is None:
    st.stop()

st.subheader(f"{playback.dataset}: {playback.query} against {', '.join(playback.database)}")
rows = ["| method | right | wrong accepts | wrong rejects | between places (not scored) |", "|---|---|---|---|---|"]
for key, c in playback.counts().items():
    rows.append(f"| {METHODS_BY_KEY[key].label} | {c[Verdict.RIGHT]} | {c[Verdict.WRONG_ACCEPT]} | "
                f"{c[Verdict.WRONG_REJECT]} | {c[Verdict.BETWEEN]} |")
st.markdown("\n".join(rows))
st.caption(
    f"Recording `{playback.recording_id}`, {playback.n_frames} frames on the `frame` timeline: press play in the "
    "viewer's time panel or drag its cursor. Methods: "
    f"{' and '.join(f'{short} = {METHODS_BY_KEY[key].label}' for key, short in RECORDED.items())}. "
    "Decision levels: INFO right, ERROR wrong accept, WARN wrong reject, DEBUG between places (not scored). "
    "Route: the query's true position in blue, answers green (right) or red (wrong). The viewer lists every "
    "recording made on this server (newest shown); pick another in its recordings panel."
)
st.iframe(playback.viewer_url, height=VIEWER_HEIGHT)
st.download_button(
    "Download the .rrd", data=playback.rrd.read_bytes, icon=":material/download:", on_click="ignore",
    file_name=f"{playback.dataset}_{playback.query}_vs_{'+'.join(playback.database)}.rrd",
    mime="application/octet-stream", help="Open it later with `rerun FILE.rrd`.",
)
