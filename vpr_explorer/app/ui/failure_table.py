"""The failure table: every query a chosen method got wrong, with its pictures, on the Evaluation page and in the
Query inspector.

One row per failing query (``views.failures``: a wrong answer, a wrong reject or an accepted
unknown-place query) under the method picked above the table: thumbnails of the query, of the
method's answer (for a rejected query, the best image of the place it came closest to
accepting) and of the true match (the query's best right database image; none for an
unknown-place query), then the kind, the method, the top candidate's score, θ and margin and
the reason sentence (``views.failures.TABLE_COLUMNS``). The kinds are filtered by a
multiselect, the rows sorted by the query, the margin or the score (``views.failures.sort_rows``:
an empty margin last), and the first ``SHOWN_ROWS`` drawn; **Download failures (CSV)**
serves every row in the same order, the same columns without the pictures.

The queries decided are the page's overview's (``views.failures.failure_queries``: every query
up to ``numbers.PAIR_BUDGET`` similarities, above it a seeded sample, which the caption says).

Selecting a row opens that query in the Query inspector: the view's ``frame`` (and, for
aligned traversals, its query traversal) becomes the row's, and the inspector's finder is set
to the row's kind and method (``inspector_find``, ``inspector_method`` in the URL), so that its
◀ previous / next ▶ walk the failures of that kind. ``show``'s ``navigate`` runs after that:
the Evaluation page switches to the inspector there; the inspector itself only reruns.
"""

from __future__ import annotations

import base64
import io
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd
import streamlit as st
from PIL import Image

from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.retrieval import METHODS_BY_KEY
from vpr_explorer.views import failures as vf
from vpr_explorer.views.numbers import LIVE_METHODS, FindKind, RetrievalPlaces

from vpr_explorer.app.ui import cache, state
from vpr_explorer.app.ui.feedback import show_error

#: Widget key of the Query inspector's "Failures" expander (its open state: the section runs only while open).
OPEN = "w_failures_open"
#: Rows drawn with their pictures at most (the CSV holds every row).
SHOWN_ROWS = 200
#: Thumbnail height in pixels, and the table's row height.
THUMB_HEIGHT = 56
ROW_HEIGHT = 64
#: The method the table starts on (the inspector's finder's default).
DEFAULT_METHOD = "margin-weighted"
#: Each kind in the multiselect.
KIND_LABELS = {
    vf.FailureKind.WRONG_ANSWER: "wrong answer (accepted, wrong place)",
    vf.FailureKind.WRONG_REJECT: "wrong reject (its right place was there)",
    vf.FailureKind.ACCEPTED_UNKNOWN: "accepted unknown (no right place in the database)",
}
#: The inspector's finder kind of each failure kind (``numbers.FindKind``).
FIND_KIND = {
    vf.FailureKind.WRONG_ANSWER: FindKind.WRONG_ANSWER,
    vf.FailureKind.WRONG_REJECT: FindKind.WRONGLY_REJECTED,
    vf.FailureKind.ACCEPTED_UNKNOWN: FindKind.ACCEPTED_UNKNOWN,
}
SORT_LABELS = {"query": "query", "margin": "margin (score − θ)", "score": "score"}
#: The picture columns of the drawn table (data URIs), before the library's columns.
PICTURES = ("query picture", "answer picture", "true picture")
#: What the drawn table shows, in order (the rest of ``TABLE_COLUMNS`` is in the CSV): the pictures and the numbers
#: first, the long reason and the method (the one picked above) last.
SHOWN_COLUMNS = ("query picture", "query", "kind", "answer picture", "answer", "true picture", "true place",
                 "true rank", "score", "θ", "margin", "reason", "method")


def methods_offered(user_theta: float | None) -> list[str]:
    """The methods the table offers: the live pages' and the image-level baseline, your own global θ when set."""
    keys = ["image-baseline", *LIVE_METHODS]
    return keys + (["global-user"] if user_theta is not None else [])


@st.cache_resource(show_spinner="Finding the failing queries…", max_entries=16)
def _failures(key: str, places: tuple, method: str, k: float, user_theta: float | None, _data: cache.Loaded,
              _places: RetrievalPlaces) -> tuple[vf.Failures, list[dict[str, object]], list[tuple]]:
    fitted = cache.fitted(_data, _places)
    result = vf.find_failures(fitted, _data.descriptors, method, top=1, k=k, user_theta=user_theta,
                              queries=vf.failure_queries(fitted))
    pictures = [vf.row_pictures(fitted, f) for f in result.failures]
    return result, vf.table_rows(fitted, result), pictures


def failures(data: cache.Loaded, places: RetrievalPlaces, method: str, *, k: float = 0.0,
             user_theta: float | None = None) -> tuple[vf.Failures, list[dict[str, object]], list[tuple]]:
    """``views.failures.find_failures`` over the page's queries, its ``table_rows`` and each row's picture files."""
    return _failures(data.key, cache.places_key(places), method, float(k), user_theta, data, places)


def data_uri(path: Path | None) -> str | None:
    """A small JPEG of an image file as a ``data:`` URI (``cache.thumbnail``), ``None`` for no file."""
    if path is None:
        return None
    thumb = cache.thumbnail(path, THUMB_HEIGHT)
    if isinstance(thumb, Image.Image):  # a file that cannot be read: the grey placeholder
        buffer = io.BytesIO()
        thumb.save(buffer, format="JPEG")
        thumb = buffer.getvalue()
    return "data:image/jpeg;base64," + base64.b64encode(thumb).decode("ascii")


def drawn(rows: Sequence[dict[str, object]], pictures: dict[int, tuple]) -> pd.DataFrame:
    """The rows as the table draws them: the pictures as data URIs, an empty true place blank, a dropped rank said."""
    frame = pd.DataFrame(list(rows), columns=list(vf.TABLE_COLUMNS))
    for i, column in enumerate(PICTURES):
        frame[column] = [data_uri(pictures[int(q)][i]) for q in frame["query"]]
    frame["true place"] = [None if p < 0 else int(p) for p in frame["true place"]]
    frame["true rank"] = [vf.rank_text(r) for r in frame["true rank"]]
    return frame


def _open(table_key: str, shown_key: str, method: str, query_traversal: str | None,
          navigate: Callable[[], None] | None) -> None:
    """A selected row: its query into the view, the finder onto its kind and method, then ``navigate``."""
    selection = st.session_state[table_key].selection
    if not selection.rows:  # a row unselected: nothing to open
        return
    query, kind = st.session_state[shown_key][selection.rows[0]]
    changes: dict[str, object] = {"frame": int(query)}
    if query_traversal is not None and query_traversal != state.view().query:
        changes["query"] = query_traversal
    state.update(**changes)
    state.set_page_params(inspector_find=FIND_KIND[vf.FailureKind(kind)].value,
                          inspector_method=method if method in [*LIVE_METHODS, "global-user"] else None)
    if navigate is not None:
        navigate()


def show(data: cache.Loaded, places: RetrievalPlaces, *, key: str, k: float = 0.0, user_theta: float | None = None,
         query_traversal: str | None = None, navigate: Callable[[], None] | None = None,
         opens: str = "in the **Query inspector**") -> list[dict[str, object]] | None:
    """The controls, the table and its CSV; the rows shown in their order (``None`` on bad input, said).

    Args:
        data, places: the dataset value and its places (the inspector's, or the Evaluation page's value).
        key: prefix of the widgets' keys (one table per page).
        k, user_theta: the thresholds' k and your own global θ (``numbers.decide_queries``).
        query_traversal: the value's query traversal, set into the view when a row is opened (aligned traversals).
        navigate: what a selected row does after the view has its query (the Evaluation page: go to the inspector).
        opens: where a selected row opens, in the caption's words.
    """
    offered = methods_offered(user_theta)
    if st.session_state.get(f"{key}_method") not in offered:
        st.session_state[f"{key}_method"] = DEFAULT_METHOD
    top = st.columns([3, 4, 2, 2], vertical_alignment="bottom")
    method = top[0].selectbox("Method", offered, format_func=lambda m: METHODS_BY_KEY[m].label, key=f"{key}_method",
                              help="The method whose failing queries are listed")
    kinds = top[1].multiselect("Kinds of failure", list(vf.FailureKind), default=list(vf.FailureKind),
                               format_func=lambda kind: KIND_LABELS[vf.FailureKind(kind)], key=f"{key}_kinds")
    by = top[2].selectbox("Sort by", vf.SORT_KEYS, format_func=SORT_LABELS.get, key=f"{key}_sort",
                          help="Margin: the top candidate's score − its θ (how far from the threshold); score: its "
                               "raw_p. A method without threshold has no margin: those rows sort last.")
    descending = top[3].toggle("largest first", value=False, key=f"{key}_descending",
                               help="On: the largest value first; off: the smallest first")
    try:
        result, rows, pictures = failures(data, places, method, k=k, user_theta=user_theta)
    except VPRInputError as exc:
        show_error(exc, hint="Pick another method, or change group/step on the **Places** page.")
        return None
    fitted = cache.fitted(data, places)
    st.caption(vf.summary_lines(result)[0] + ".")
    if result.sampled:
        st.caption(f"A sample: the {len(result.decided):,} queries the page decides, seeded, of the "
                   f"{result.n_queries:,} (every query would be {result.n_queries * len(fitted.model.images):.1e} "
                   "query × database similarities): each kind's count is of these.")
    nothing = vf.accepts_nothing(fitted, method, k=k, user_theta=user_theta)
    if nothing:
        st.caption(nothing)
    for note in result.notes:
        st.caption(f"note: {note}")
    wanted = {vf.FailureKind(kind).value for kind in kinds}
    chosen = vf.sort_rows([r for r in rows if r["kind"] in wanted], by, descending=descending)
    if not chosen:
        st.info(f"No failing query of the kinds chosen under {METHODS_BY_KEY[method].label}.",
                icon=":material/check_circle:")
        return chosen
    shown = chosen[:SHOWN_ROWS]
    by_query = {f.query: p for f, p in zip(result.failures, pictures)}
    signature = zlib.crc32(repr((data.key, cache.places_key(places), method, k, user_theta, sorted(wanted), by,
                                 descending)).encode())
    table_key, shown_key = f"{key}_table_{signature:08x}", f"{key}_shown"
    st.session_state[shown_key] = [(int(r["query"]), str(r["kind"])) for r in shown]
    st.caption((f"The first {len(shown)} of {len(chosen)} rows in this order; the CSV holds all {len(chosen)}. "
                if len(shown) < len(chosen) else f"{len(chosen)} rows. ")
               + f"Select a row (the box at its left): its query opens {opens}.")
    st.dataframe(drawn(shown, by_query), key=table_key, hide_index=True, width="stretch",
                 column_order=SHOWN_COLUMNS, row_height=ROW_HEIGHT, selection_mode="single-row", placeholder="—",
                 on_select=lambda: _open(table_key, shown_key, method, query_traversal, navigate),
                 column_config=_column_config())
    st.download_button("Download failures (CSV)", vf.table_csv(chosen), mime="text/csv", key=f"{key}_csv",
                       file_name=f"failures-{method}-{'-'.join(sorted(wanted))}.csv", on_click="ignore")
    return chosen


def _column_config() -> dict:
    number = st.column_config.NumberColumn
    return {
        "query picture": st.column_config.ImageColumn("query", width="small"),
        "query": number("#", width=44, help="The query's index among the queries (its frame on aligned traversals)"),
        "kind": st.column_config.TextColumn("kind", width=104, help="; ".join(vf.KIND_WORDS.values())),
        "method": st.column_config.TextColumn("method", width=130),
        "answer picture": st.column_config.ImageColumn(
            "answer", width="small", help="The answered place's best image; for a rejected query, the best image of "
                                          "the place it came closest to accepting"),
        "answer": st.column_config.TextColumn("answered", width=150,
                                              help="The answered place, or 'rejected' and the place the query came "
                                                   "closest to"),
        "true picture": st.column_config.ImageColumn(
            "true match", width="small", help="The query's best right database image (none: an unknown-place query)"),
        "true place": number("true place", width=68),
        "true rank": st.column_config.TextColumn("true rank", width=68,
                                                 help="The method's rank of the true place ('dropped': below its "
                                                      "threshold)"),
        "score": number("score", format="%.3f", width=56,
                        help="The top candidate's raw_p (the answer; a rejected query's closest place): its best "
                             "similarity. s(q, i) for the image-level baseline."),
        "θ": number("θ", format="%.3f", width=56, help="The top candidate's threshold: θ_p(k) of its place, or the "
                                                         "global θ; empty for a method without threshold"),
        "margin": number("margin", format="%+.3f", width=64, help="score − θ: above 0 the place passes the threshold"),
        "reason": st.column_config.TextColumn("reason", width="large", help="The method's decision in words"),
    }
