"""Playback: a query traversal decided frame by frame, watched in rerun's web viewer.

Any frame of the recording opens in the Query inspector (same query traversal, frame, k
and group/step), where each method's decision is explained and drawn.
"""

import numpy as np
import streamlit as st

from vpr_explorer.method.places import BETWEEN_PLACES_RULE
from vpr_explorer.recording import RECORDED, Verdict, frame_verdicts, record_playback
from vpr_explorer.method.retrieval import METHODS_BY_KEY

from vpr_explorer.app.ui import state
from vpr_explorer.app.ui.current import current
from vpr_explorer.app.ui.feedback import progress_reporter, stop_on_input_error
from vpr_explorer.app.ui.routing import ensure_routed, page_file
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
    key=f"w_playback_database_{query}",
    help="The database is the set of traversals the query frames are matched against: each place's threshold θ_p "
         "is fitted on these traversals' images only (their scores against the other places), and every answer "
         "is one of their images. The Query inspector always uses every traversal but the query.",
)
k = cols[2].slider("k: θ_p(k) = θ_p + k·s_p (k = 0 is the paper)", K_RANGE[0], K_RANGE[1], step=0.25,
                   help="θ_p(k) = θ_p + k·s_p, where s_p is the standard deviation of the place's negative mixture "
                        "(its database images' scores against other places): k = 0 is the paper's threshold, and "
                        "raising k moves every place's threshold up, rejecting more frames.",
                   **state.bind("w_playback_k", "k", float(min(max(v.k, K_RANGE[0]), K_RANGE[1]))))

if st.button("Record and play", type="primary", icon=":material/play_circle:", disabled=not database,
             help="Decides every frame of the query traversal against the database under the paper's method and "
                  "the place-level baseline, writes the decisions, scores and images to a rerun recording (.rrd) "
                  "and shows it in the viewer below."):
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
    "Decision levels: INFO right, ERROR wrong accept, WARN wrong reject, DEBUG between places, not scored. "
    f"{BETWEEN_PLACES_RULE} "
    "Route: the query's true position in blue, answers green (right) or red (wrong). The viewer lists every "
    "recording made on this server (newest shown); pick another in its recordings panel."
)
st.iframe(playback.viewer_url, height=VIEWER_HEIGHT)
st.download_button(
    "Download the .rrd", data=playback.rrd.read_bytes, icon=":material/download:", on_click="ignore",
    file_name=f"{playback.dataset}_{playback.query}_vs_{'+'.join(playback.database)}.rrd",
    mime="application/octet-stream", help="Open it later with `rerun FILE.rrd`.",
)

st.subheader("Open a frame in the Query inspector")
if playback.dataset != ds.name or playback.query not in ds.traversals:
    st.info(f"This recording is of {playback.dataset}; the app now looks at {ds.name}: record again to open its "
            "frames in the Query inspector.", icon=":material/info:")
    st.stop()
dec = playback.decisions
frames = ds.image_frame[dec.query_images]
verdicts = {key: frame_verdicts(dec, key) for key in RECORDED}
wrong = [int(f) for f, verdict in zip(frames, verdicts["margin-weighted"])
         if verdict in (Verdict.WRONG_ACCEPT, Verdict.WRONG_REJECT)]
default = v.frame if v.frame is not None and 0 <= v.frame < playback.n_frames else (wrong[0] if wrong else 0)
pick, said, go = st.columns([1, 3, 2], vertical_alignment="bottom")
pick.number_input(
    "frame", 0, playback.n_frames - 1, step=1, **state.bind("w_playback_frame", "frame", int(default)),
    help=f"A frame number of the query traversal {playback.query} (0 to {playback.n_frames - 1}): the frame the "
         "viewer's time cursor shows on its `frame` timeline. The button opens the same query frame in the Query "
         f"inspector. Frames the paper's method got wrong here: {', '.join(map(str, wrong[:12])) or 'none'}"
         f"{' …' if len(wrong) > 12 else ''}.",
)
frame = int(state.view().frame if state.view().frame is not None else default)
row = int(np.flatnonzero(frames == frame)[0]) if (frames == frame).any() else None
if row is not None:
    said.markdown(f"Frame **{frame}**: " + "; ".join(
        f"{short} ({METHODS_BY_KEY[key].label}): **{verdicts[key][row]}**" for key, short in RECORDED.items()))
if go.button(f"Open frame {frame} in the Query inspector", key="w_playback_inspect", icon=":material/search:",
             help="Shows this query frame in the Query inspector: its candidate places under every method, their "
                  "thresholds and margins, and each decision in words."):
    state.update(query=playback.query, frame=frame)
    st.switch_page(page_file("inspector"))
if tuple(playback.database) != tuple(t for t in ds.traversals if t != playback.query):
    st.caption(f"This recording's database is {', '.join(playback.database)}; the inspector's is every traversal but "
               f"{playback.query} ({', '.join(t for t in ds.traversals if t != playback.query)}), so its answers "
               "can differ.")
