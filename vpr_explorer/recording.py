"""Traversal playback with rerun: a query traversal decided frame by frame against a database.

The one module that talks to rerun. Every recording is an explicit
``rerun.RecordingStream`` (never rerun's global one: several browser sessions may record
at once). On one ``frame`` timeline it logs, for each query frame:

| entity                                   | what                                                        |
|------------------------------------------|-------------------------------------------------------------|
| ``query``                                | the query image (its file's bytes, original size)           |
| ``match/paper``, ``match/baseline``      | the database image behind each method's answer (cleared when rejected) |
| ``decision/paper``, ``decision/baseline``| the answer and whether it was right, as a text log; level INFO right, ERROR wrong accept, WARN wrong reject, DEBUG between places (not scored) |
| ``scores/<method>/{raw,theta,margin}``   | raw_p, θ_p and raw_p − θ_p of the method's best place         |
| ``place/{true,paper,baseline}``          | the true place and each answered place                       |
| ``route/query``, ``route/<method>``      | the query's true position and the answered image's position  |

and, static: ``route/path`` and ``route/places`` (the route, from ``Dataset.positions`` or,
without positions, frame indices on a line), ``thresholds/{weighted,simple}`` (θ_p of every
place) and ``summary`` (settings and counts). ``playback_blueprint`` lays them out.

"paper" is the paper's method (margin rule, weighted θ: ``margin-weighted``), "baseline"
the place-level baseline (``place-baseline``). The baseline has no threshold; its θ_p and
margin series show where the paper's weighted θ_p puts the place it picked.

Images are read from disk one frame at a time and logged as encoded files, so a long
traversal never holds all its images in memory (give the recording a sink first,
``save``/``set_sinks``: one without a sink buffers everything).

Entry points, from the most to the least given: ``log_traversal`` (decisions already
made) < ``record_traversal`` (decides, then logs) < ``save_traversal`` (a new recording
written to an ``.rrd``, optionally served) < ``record_playback`` (places and database
thresholds of a loaded dataset) < ``record_dataset`` (a dataset path or ``"demo"``; the
``record`` command). ``viewer_servers`` starts rerun's gRPC server and bundled web viewer
once per process.
"""

from __future__ import annotations

import atexit
import shutil
import socket
import tempfile
import threading
import urllib.parse
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from vpr_explorer.method.database import DatabaseModel, TraversalDecisions, Verdict, decide_traversal, fit_database
from vpr_explorer.data.traversals import Dataset, load_dataset
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import BETWEEN_PLACES_RULE, Places, PlaceSpec, between_places, make_places
from vpr_explorer.settings import check_cache_root
from vpr_explorer.method.retrieval import METHODS_BY_KEY

APPLICATION_ID = "vpr_explorer"
TIMELINE = "frame"
PAPER = "margin-weighted"
BASELINE = "place-baseline"
RECORDED: dict[str, str] = {PAPER: "paper", BASELINE: "baseline"}
"""Method key -> the short name used in entity paths."""

ENCODED_SUFFIXES = frozenset({".jpg", ".jpeg", ".png"})
"""Logged as the file's bytes; other formats are decoded and logged as pixels."""

Progress = Callable[[int, int], None]


LEVELS = {
    Verdict.RIGHT: rr.TextLogLevel.INFO,
    Verdict.WRONG_ACCEPT: rr.TextLogLevel.ERROR,
    Verdict.WRONG_REJECT: rr.TextLogLevel.WARN,
    Verdict.BETWEEN: rr.TextLogLevel.DEBUG,
}

_COLORS = {
    Verdict.RIGHT: (60, 180, 75),
    Verdict.WRONG_ACCEPT: (230, 25, 75),
    Verdict.WRONG_REJECT: (245, 130, 48),
    Verdict.BETWEEN: (150, 150, 150),
}
_SERIES = {"raw": (31, 119, 180), "theta": (214, 39, 40), "margin": (44, 160, 44)}
_SERIES_NAMES = {"raw": "raw_p", "theta": "θ_p (weighted)", "margin": "margin raw_p − θ_p"}
_ROUTE = (120, 120, 120)
_QUERY = (31, 119, 255)
_MARKERS = {"true": "Circle", "paper": "Cross", "baseline": "Diamond"}
_PLACE_COLORS = {"true": (200, 200, 200), "paper": (31, 119, 180), "baseline": (255, 127, 14)}


# --------------------------------------------------------------------------- what is logged


def frame_verdicts(decisions: TraversalDecisions, key: str) -> np.ndarray:
    """``(n_frames,)`` ``Verdict`` values of one method over the query frames.

    A frame with no right place (between places) is not scored (``places.BETWEEN_PLACES_RULE``,
    as in the traversal protocol); otherwise right = accepted with the true place at rank 1.
    """
    o = decisions.outcomes[key]
    known = ~between_places(decisions.truth)
    out = np.where(o.right, Verdict.RIGHT.value,
                   np.where(o.accepted, Verdict.WRONG_ACCEPT.value, Verdict.WRONG_REJECT.value))
    return np.where(known, out, Verdict.BETWEEN.value).astype(object)


def verdict_counts(decisions: TraversalDecisions, key: str) -> dict[Verdict, int]:
    """How many frames got each verdict under one method."""
    v = frame_verdicts(decisions, key)
    return {verdict: int((v == verdict.value).sum()) for verdict in Verdict}


def best_places(decisions: TraversalDecisions, key: str) -> np.ndarray:
    """``(n_frames,)`` the place whose scores are plotted for a method.

    The answered place; for a rejected frame, the place that came closest (highest
    raw_p − θ_p), which is the one the paper's rule would have answered.
    """
    o = decisions.outcomes[key]
    method = METHODS_BY_KEY[key]
    if method.threshold is None:
        ranking = decisions.raw
    else:
        with np.errstate(invalid="ignore"):
            ranking = decisions.raw - np.asarray(decisions.thresholds[method.threshold], dtype=np.float64)
    closest = np.argmax(np.where(np.isfinite(ranking), ranking, -np.inf), axis=1)
    return np.where(o.accepted, o.answer_place, closest)


def score_series(decisions: TraversalDecisions, key: str) -> dict[str, np.ndarray]:
    """``{"raw", "theta", "margin"}`` -> ``(n_frames,)`` of each frame's best place (``best_places``).

    θ is the paper's weighted θ_p (with the decisions' k) for both methods.
    """
    p = best_places(decisions, key)
    rows = np.arange(len(p))
    theta = np.broadcast_to(np.asarray(decisions.thresholds["weighted"], dtype=np.float64), decisions.raw.shape[1:])
    raw = decisions.raw[rows, p]
    return {"raw": raw, "theta": theta[p], "margin": raw - theta[p]}


def describe_frames(decisions: TraversalDecisions, key: str) -> list[str]:
    """One method's decision for every frame in words, e.g.
    "accepted as place 7 (right): raw 0.812, threshold 0.460, margin +0.352"."""
    o = decisions.outcomes[key]
    method = METHODS_BY_KEY[key]
    theta = np.broadcast_to(np.asarray(decisions.thresholds["weighted"], dtype=np.float64), decisions.raw.shape[1:])
    closest = best_places(decisions, key)
    verdicts = frame_verdicts(decisions, key)
    texts = []
    for frame in range(len(o.answer_place)):
        raw = decisions.raw[frame]

        def scores(p: int) -> str:
            text = f"raw {raw[p]:.3f}"
            if method.threshold is not None:
                text += f", threshold {theta[p]:.3f}, margin {raw[p] - theta[p]:+.3f}"
            return text

        answer = int(o.answer_place[frame])
        if answer >= 0:
            head, body = f"accepted as place {answer}", scores(answer)
        else:
            c = int(closest[frame])
            head, body = "rejected", f"every place scored below its threshold; the closest, place {c}: {scores(c)}"
        verdict = Verdict(verdicts[frame])
        if verdict is Verdict.BETWEEN:
            texts.append(f"{head} (not scored: the frame lies between places): {body}")
            continue
        if verdict is Verdict.RIGHT:
            texts.append(f"{head} (right): {body}")
            continue
        truth = np.flatnonzero(decisions.truth[frame])
        true = int(truth[np.argmax(raw[truth])])
        rank = o.rank[frame]
        if verdict is Verdict.WRONG_REJECT:
            why = f"the query is place {true} ({scores(true)})"
        elif not np.isfinite(rank):
            why = f"the true place {true} was dropped ({scores(true)})"
        elif rank == 1:
            why = f"the true place {true} ties with it at the top, and ties count against the query"
        else:
            why = f"the true place {true} ranked {int(rank)} ({scores(true)})"
        texts.append(f"{head} (wrong: {why}): {body}")
    return texts


def route_positions(dataset: Dataset) -> np.ndarray:
    """``(n_frames, 2)`` where each frame lies: ``Dataset.positions``, else ``(frame, 0)`` on a line."""
    if dataset.positions is not None:
        return np.asarray(dataset.positions, dtype=np.float64)
    f = np.arange(dataset.n_frames, dtype=np.float64)
    return np.stack([f, np.zeros_like(f)], axis=1)


#: Longest view title the viewer shows whole in a third of the Playback page's width.
TITLE_CHARS = 40


def playback_blueprint(query: str, database: Sequence[str]) -> rrb.Blueprint:
    """Query and both answers on top, the score series below, route, decisions and thresholds last.

    View titles stay within ``TITLE_CHARS`` so that none is cut in a third of the page;
    colours and units are in each plot's legend instead (the series' names,
    ``_SERIES_NAMES``: rerun's plots have no axis titles) and in the summary. The summary
    shares the widest panel with the decision log, word-wrapped.
    """
    legend = rrb.PlotLegend(corner=rrb.Corner2D.LeftTop, visible=True)
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial2DView(origin="query", name=_title(f"query ({query})")),
                rrb.Spatial2DView(origin="match/paper", name="paper's answer: margin, weighted θ"),
                rrb.Spatial2DView(origin="match/baseline", name="place-level baseline's answer"),
            ),
            rrb.Horizontal(
                rrb.TimeSeriesView(origin="scores/paper", name="paper: similarity per frame",
                                   plot_legend=legend),
                rrb.TimeSeriesView(origin="scores/baseline", name="baseline: similarity per frame",
                                   plot_legend=legend),
                rrb.TimeSeriesView(origin="place", name="place: true (grey) and answers", plot_legend=legend),
            ),
            rrb.Horizontal(
                rrb.Spatial2DView(origin="route", name="route: query blue, answers"),
                rrb.Tabs(
                    rrb.TextDocumentView(origin="summary", name="summary",
                                         format_options=rrb.archetypes.TextDocumentFormat(word_wrap=True)),
                    rrb.TextLogView(origin="decision", name="decisions"),
                    rrb.BarChartView(origin="thresholds/weighted", name="θ_p weighted (paper) per place"),
                    rrb.BarChartView(origin="thresholds/simple", name="θ_p simple per place"),
                ),
                column_shares=[2, 5],
            ),
            row_shares=[3, 3, 4],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE),
    )


def _title(text: str) -> str:
    """``text`` cut to ``TITLE_CHARS`` with an ellipsis (a traversal name can be long)."""
    return text if len(text) <= TITLE_CHARS else text[:TITLE_CHARS - 1] + "…"


def _image(path: Path) -> rr.AsComponents:
    """The image file as rerun logs it; an unreadable one is an error (rerun would only warn and log nothing)."""
    from PIL import Image, UnidentifiedImageError

    try:
        if path.suffix.lower() in ENCODED_SUFFIXES:
            return rr.EncodedImage(contents=path.read_bytes(), media_type=rr.components.MediaType.guess_from_path(path))
        with Image.open(path) as im:
            return rr.Image(np.asarray(im.convert("RGB")))
    except (OSError, UnidentifiedImageError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise VPRInputError(f"{path}: cannot read the image ({why}); restore the file and record again") from exc


def _summary(
    dataset: Dataset, places: Places, model: DatabaseModel, decisions: TraversalDecisions, query: str,
    descriptor: str | None, k: float,
) -> str:
    db = ", ".join(dataset.traversals[t] for t in model.traversals)
    lines = [
        f"# {dataset.name}: {query} against {db}",
        "",
        f"- places: {places.describe()}",
        f"- descriptor: {descriptor or 'not given'}",
        f"- thresholds: θ_p + k·s_p with k = {k:g}, from the database images only "
        "(weighted θ uses the normalised weights wᵢτᵢ² / Σⱼ wⱼτⱼ²)",
        f"- {len(decisions.query_images)} query frames, {int((~between_places(decisions.truth)).sum())} in a place",
        f"- {BETWEEN_PLACES_RULE}",
        "",
        "## Decisions",
        "",
    ]
    # One short line per method, not a wide table: the viewer's text panel would cut its columns.
    for key, short in RECORDED.items():
        c = verdict_counts(decisions, key)
        scored = c[Verdict.RIGHT] + c[Verdict.WRONG_ACCEPT] + c[Verdict.WRONG_REJECT]
        recall = f"{100 * c[Verdict.RIGHT] / scored:.1f} %" if scored else "— (no frame in a place)"
        lines.append(f"- **{short}** ({METHODS_BY_KEY[key].label}): Recall@1 {recall}; {c[Verdict.RIGHT]} right, "
                     f"{c[Verdict.WRONG_ACCEPT]} wrong accepts, {c[Verdict.WRONG_REJECT]} wrong rejects, "
                     f"{c[Verdict.BETWEEN]} between places (not scored)")
    lines += [
        "",
        "## Plots",
        "",
        f"- similarity per frame: {', '.join(_SERIES_NAMES.values())} of the method's best place "
        "(the answer, or for a rejected frame the closest place), against the frame number",
        "- place: the true place id and each answered place id, against the frame number",
        "- route: the query's true position (blue), each answer's position (green right, red wrong)",
    ]
    return "\n".join(lines) + "\n"


def log_traversal(
    recording: rr.RecordingStream,
    dataset: Dataset,
    places: Places,
    model: DatabaseModel,
    decisions: TraversalDecisions,
    *,
    descriptor: str | None = None,
    k: float = 0.0,
    progress: Progress | None = None,
) -> None:
    """Log decided query frames to ``recording`` (entities in the module docstring).

    Static entities and every series go first as columns; then the images, one frame at
    a time, read from disk. ``descriptor`` and ``k`` only label the summary.
    """
    qi = np.asarray(decisions.query_images)
    frames = dataset.image_frame[qi].astype(np.int64)
    query = dataset.traversals[int(dataset.image_traversal[qi[0]])]
    times = [rr.TimeColumn(TIMELINE, sequence=frames)]
    positions = route_positions(dataset)
    theta = {name: np.broadcast_to(np.asarray(decisions.thresholds[name], dtype=np.float64), (places.n_places,))
             for name in ("weighted", "simple")}

    recording.log("summary", rr.TextDocument(_summary(dataset, places, model, decisions, query, descriptor, k),
                                             media_type=rr.MediaType.MARKDOWN), static=True)
    for name, values in theta.items():
        recording.log(f"thresholds/{name}", rr.BarChart(np.nan_to_num(values)), static=True)
    recording.log("route/path", rr.LineStrips2D([positions], colors=[_ROUTE],
                                                radii=rr.components.Radius.ui_points(1.5)), static=True)
    # A place's mark sits at the mean of its frames (the middle frame of a group).
    in_place = places.frame_place >= 0
    counts = np.bincount(places.frame_place[in_place], minlength=places.n_places)
    sums = np.bincount(places.frame_place[in_place], weights=np.flatnonzero(in_place), minlength=places.n_places)
    centres = np.rint(sums / np.maximum(counts, 1)).astype(np.int64)
    recording.log("route/places", rr.Points2D(
        positions[centres], radii=rr.components.Radius.ui_points(3.0), colors=[_ROUTE],
        labels=[f"place {p}: θ {theta['weighted'][p]:.3f}" for p in range(places.n_places)],
        show_labels=False,  # shown on hover: drawn, they hide the route
    ), static=True)

    known = decisions.truth.any(axis=1)
    true_place = np.argmax(decisions.truth, axis=1)
    recording.log("place/true", rr.SeriesPoints(colors=[_PLACE_COLORS["true"]], markers=[_MARKERS["true"]],
                                                names=["true place"]), static=True)
    recording.send_columns("place/true", indexes=[rr.TimeColumn(TIMELINE, sequence=frames[known])],
                           columns=rr.Scalars.columns(scalars=true_place[known].astype(np.float64)))
    recording.send_columns("route/query", indexes=times, columns=rr.Points2D.columns(
        positions=positions[frames], colors=np.tile(_QUERY, (len(frames), 1)),
        radii=np.full(len(frames), rr.components.Radius.ui_points(6.0), dtype=np.float32),
    ))

    verdicts = {key: frame_verdicts(decisions, key) for key in RECORDED}
    for key, short in RECORDED.items():
        o = decisions.outcomes[key]
        label = METHODS_BY_KEY[key].label
        for name, values in score_series(decisions, key).items():
            path = f"scores/{short}/{name}"
            recording.log(path, rr.SeriesLines(colors=[_SERIES[name]], names=[_SERIES_NAMES[name]]), static=True)
            recording.send_columns(path, indexes=times, columns=rr.Scalars.columns(scalars=values))
        accepted = o.accepted
        recording.log(f"place/{short}", rr.SeriesPoints(colors=[_PLACE_COLORS[short]], markers=[_MARKERS[short]],
                                                        names=[f"answer ({label})"]), static=True)
        recording.send_columns(f"place/{short}", indexes=[rr.TimeColumn(TIMELINE, sequence=frames[accepted])],
                               columns=rr.Scalars.columns(scalars=o.answer_place[accepted].astype(np.float64)))
        texts = describe_frames(decisions, key)
        recording.send_columns(f"decision/{short}", indexes=times, columns=rr.TextLog.columns(
            text=[f"frame {f} · {label}: {t}" for f, t in zip(frames, texts)],
            level=[LEVELS[Verdict(v)] for v in verdicts[key]],
        ))
        # One point per accepted frame, none for a rejected one (an empty batch clears it).
        answer_frames = dataset.image_frame[model.images[np.maximum(o.answer_image, 0)]]
        recording.send_columns(f"route/{short}", indexes=times, columns=rr.Points2D.columns(
            positions=positions[answer_frames[accepted]],
            colors=np.array([_COLORS[Verdict(v)] for v in verdicts[key][accepted]], dtype=np.uint8).reshape(-1, 3),
            radii=np.full(int(accepted.sum()), rr.components.Radius.ui_points(4.5), dtype=np.float32),
        ).partition(accepted.astype(np.int64)))

    image_paths = dataset.image_paths
    for i, (q, f) in enumerate(zip(qi, frames)):
        recording.set_time(TIMELINE, sequence=int(f))
        recording.log("query", _image(image_paths[q]))
        for key, short in RECORDED.items():
            a = int(decisions.outcomes[key].answer_image[i])
            recording.log(f"match/{short}", _image(image_paths[model.images[a]]) if a >= 0 else rr.Clear(recursive=False))
        if progress is not None:
            progress(i + 1, len(qi))
    recording.reset_time()


# --------------------------------------------------------------------------- recording


def new_recording(recording_id: str | None = None) -> rr.RecordingStream:
    """A fresh explicit recording of this application (never rerun's global one), on ``frame`` time only."""
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id or uuid.uuid4().hex)
    rec.set_log_time_enabled(False)
    return rec


def _check_inputs(dataset: Dataset, places: Places, descriptors: np.ndarray, model: DatabaseModel) -> None:
    if len(descriptors) != dataset.n_images:
        raise VPRInputError(
            f"{len(descriptors)} descriptors for {dataset.n_images} images of {dataset.name!r}: "
            "compute them for this dataset"
        )
    if len(places.frame_place) != dataset.n_frames:
        raise VPRInputError(
            f"the places cover {len(places.frame_place)} frames but every traversal of {dataset.name!r} has "
            f"{dataset.n_frames}: make the places from this dataset"
        )
    if model.n_places != places.n_places or (len(model.images) and model.images.max() >= dataset.n_images):
        raise VPRInputError("the database model was fitted on other places or another dataset: fit it on these")


def record_traversal(
    dataset: Dataset,
    places: Places,
    descriptors: np.ndarray,
    model: DatabaseModel,
    query_traversal: str | int,
    *,
    recording: rr.RecordingStream,
    k: float = 0.0,
    tolerance: int = 0,
    descriptor: str | None = None,
    progress: Progress | None = None,
) -> TraversalDecisions:
    """Decide every frame of ``query_traversal`` against ``model`` and log it to ``recording``.

    Args:
        descriptors: ``(n_images, D)`` of ``dataset``.
        k: thresholds θ_p + k·s_p (0: the paper's).
        tolerance: frames of slack for a right place, as in ``decide_traversal``.
        descriptor: its name, for the summary.
        progress: ``progress(done, total)`` after each logged frame.
    Returns:
        the library's decisions, exactly what was logged.
    """
    _check_inputs(dataset, places, descriptors, model)
    decisions = decide_traversal(model, descriptors, dataset, places, query_traversal, k=k, tolerance=tolerance)
    log_traversal(recording, dataset, places, model, decisions, descriptor=descriptor, k=k, progress=progress)
    return decisions


def check_output(path: str | Path) -> Path:
    """``path`` as an ``.rrd`` file that can be written, or a ``VPRInputError`` saying why not."""
    path = Path(path).expanduser()
    if path.suffix.lower() != ".rrd":
        raise VPRInputError(f"{path}: a rerun recording needs the .rrd suffix, e.g. {path.with_suffix('.rrd')}")
    if path.is_dir():
        raise VPRInputError(f"{path}: is a folder; give a file name such as {path / 'run.rrd'}")
    if path.parent.exists() and not path.parent.is_dir():
        raise VPRInputError(f"{path}: {path.parent} is a file, not a folder; pick another path")
    if not path.parent.is_dir():
        raise VPRInputError(f"{path}: the folder {path.parent} does not exist; create it or pick another path")
    existed = path.exists()
    try:
        with path.open("ab"):
            pass
    except OSError as exc:
        raise VPRInputError(f"{path}: cannot write the recording ({exc.strerror}); pick a writable path") from exc
    if not existed:
        path.unlink(missing_ok=True)
    return path


def check_record_options(dataset: Dataset, *, k: float, tolerance: int) -> None:
    """A recording's numeric options, or a ``VPRInputError`` naming the one at fault and its limit."""
    from vpr_explorer.pipeline import check_finite, check_whole

    check_finite("k", k, example="0 for the paper's θ_p, 1 for θ_p + s_p")
    check_whole("tolerance", tolerance, low=0, high=dataset.n_frames,
                why=f" (frames of slack; {dataset.name!r} has {dataset.n_frames:,} frames)")


# --------------------------------------------------------------------------- serving


SERVER_MEMORY_LIMIT = "1GiB"
"""What the gRPC server buffers for viewers that connect late; the oldest data goes first."""


@dataclass(frozen=True)
class ViewerServers:
    """The process's rerun gRPC server and bundled web viewer, both reached on 127.0.0.1."""

    grpc_url: str
    web_port: int

    @property
    def viewer_url(self) -> str:
        """The web viewer, connected to the gRPC server."""
        return f"http://127.0.0.1:{self.web_port}/?url={urllib.parse.quote(self.grpc_url, safe='')}"


_lock = threading.Lock()
_servers: ViewerServers | None = None
_server_owner: rr.RecordingStream | None = None
"""The recording that owns the gRPC server: rerun shuts the server down when it goes away."""
_playback_dir: Path | None = None


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def viewer_servers() -> ViewerServers:
    """Start the gRPC server and the bundled web viewer, once per process; later calls reuse them.

    Recordings reach the server through a ``GrpcSink``; the server keeps what it received
    (up to ``SERVER_MEMORY_LIMIT``) for every viewer that connects, so every recording
    made in this process is listed in the viewer, the newest one shown. rerun 0.41 binds
    both servers on all interfaces (it has no host option); the URLs use 127.0.0.1.
    """
    global _servers, _server_owner
    with _lock:
        if _servers is None:
            owner = rr.RecordingStream(APPLICATION_ID, recording_id="playback-server")
            owner.send_recording_name("playback server (holds no data)")
            grpc_url = owner.serve_grpc(grpc_port=_free_port(), server_memory_limit=SERVER_MEMORY_LIMIT)
            web_port = _free_port()
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc_url)
            _server_owner = owner
            _servers = ViewerServers(grpc_url=grpc_url, web_port=web_port)
        return _servers


def playback_dir() -> Path:
    """A folder for this process's recordings, removed when the process exits."""
    global _playback_dir
    with _lock:
        if _playback_dir is None:
            _playback_dir = Path(tempfile.mkdtemp(prefix="vpr_explorer_playback_"))
            atexit.register(shutil.rmtree, _playback_dir, True)
        return _playback_dir


# --------------------------------------------------------------------------- end to end


@dataclass(frozen=True, eq=False)
class Playback:
    """A recorded traversal: where its ``.rrd`` is, what was decided and where to watch it.

    Attributes:
        rrd: the recording file.
        recording_id: rerun's recording id (the viewer lists recordings by it).
        dataset: the dataset name.
        database: database traversal names.
        query: query traversal name.
        decisions: the library's decisions, exactly what was logged.
        viewer_url: the bundled web viewer showing it, when it was served.
    """

    rrd: Path
    recording_id: str
    dataset: str
    database: tuple[str, ...]
    query: str
    decisions: TraversalDecisions
    viewer_url: str | None = None

    @property
    def n_frames(self) -> int:
        return len(self.decisions.query_images)

    def counts(self) -> dict[str, dict[Verdict, int]]:
        """Method key -> frames per verdict, for the recorded methods."""
        return {key: verdict_counts(self.decisions, key) for key in RECORDED}

    def describe(self) -> str:
        """One line per recorded method, e.g. "margin, weighted θ: 45 right, 3 wrong accepts, …"."""
        lines = [f"{self.n_frames} frames of {self.query} against {', '.join(self.database)} ({self.dataset})"]
        for key, c in self.counts().items():
            lines.append(
                f"{METHODS_BY_KEY[key].label}: {c[Verdict.RIGHT]} right, {c[Verdict.WRONG_ACCEPT]} wrong accepts, "
                f"{c[Verdict.WRONG_REJECT]} wrong rejects ({c[Verdict.BETWEEN]} frames between places, not scored)"
            )
        return "\n".join(lines)


def _traversal_choice(database: Sequence[str], queries: str) -> list[str]:
    database = list(dict.fromkeys(database))
    if not database:
        raise VPRInputError("database: choose at least one database traversal")
    if queries in database:
        raise VPRInputError(f"queries={queries!r} is also a database traversal; pick another query traversal")
    return database


def load_traversals(source: str | Path, database: Sequence[str], queries: str) -> Dataset:
    """The dataset at ``source`` (or ``"demo"``) with the chosen traversals checked.

    A traversal-folder dataset is read with only these traversals, so the loader checks
    that they exist and have equal lengths (frame i must be the same spot in each), and
    the folder's other traversals do not matter.
    """
    from vpr_explorer.pipeline import DEMO, resolve_dataset

    database = _traversal_choice(database, queries)
    try:
        if str(source) == DEMO:
            dataset = resolve_dataset(DEMO)
        else:
            dataset = load_dataset(source, traversals=[*database, queries])
        for name in (*database, queries):
            dataset.traversal_index(name)
    except VPRInputError as exc:
        raise VPRInputError(f"database={database}, queries={queries!r}: {exc}") from None
    return dataset


def save_traversal(
    out: str | Path,
    dataset: Dataset,
    places: Places,
    descriptors: np.ndarray,
    model: DatabaseModel,
    query_traversal: str | int,
    *,
    serve: bool = False,
    k: float = 0.0,
    tolerance: int = 0,
    descriptor: str | None = None,
    recording_id: str | None = None,
    progress: Progress | None = None,
) -> Playback:
    """``record_traversal`` into a new recording written to the ``.rrd`` file ``out``, with its blueprint.

    Args:
        serve: also stream it to this process's viewer servers (``viewer_servers``); the
            returned ``Playback.viewer_url`` shows it.
    """
    out = check_output(out)
    check_record_options(dataset, k=k, tolerance=tolerance)
    query = dataset.traversals[dataset.traversal_index(query_traversal)]
    database = [dataset.traversals[t] for t in model.traversals]
    servers = viewer_servers() if serve else None
    rec = new_recording(recording_id)
    # Written beside ``out`` and renamed over it once complete: an interrupted or failed run
    # leaves an existing recording as it was (and no partial file).
    partial = out.with_name(f".{out.stem}.{uuid.uuid4().hex[:8]}.partial.rrd")
    sinks: list = [rr.FileSink(partial)]
    if servers is not None:
        sinks.append(rr.GrpcSink(servers.grpc_url))
    try:
        try:
            rec.set_sinks(*sinks)
        except RuntimeError as exc:
            raise VPRInputError(f"{out}: cannot write the recording ({exc}); pick a writable path") from exc
        rec.send_recording_name(f"{dataset.name}: {query} against {', '.join(database)}")
        rec.send_blueprint(playback_blueprint(query, database))
        try:
            decisions = record_traversal(dataset, places, descriptors, model, query, recording=rec, k=k,
                                         tolerance=tolerance, descriptor=descriptor, progress=progress)
        finally:
            # Sends what is buffered and closes the file (writing its footer); the served copy
            # lives on in the gRPC server, which ``_server_owner`` keeps running.
            rec.flush()
            rec.disconnect()
        try:
            partial.replace(out)
        except OSError as exc:
            raise VPRInputError(f"{out}: cannot write the recording ({exc.strerror}); pick a writable path") from exc
    finally:
        partial.unlink(missing_ok=True)
    return Playback(rrd=out, recording_id=rec.get_recording_id(), dataset=dataset.name, database=tuple(database),
                    query=query, decisions=decisions, viewer_url=servers.viewer_url if servers else None)


def record_playback(
    dataset: Dataset,
    descriptors: np.ndarray,
    spec: PlaceSpec | None,
    *,
    database: Sequence[str],
    queries: str,
    out: str | Path | None = None,
    serve: bool = False,
    k: float = 0.0,
    tolerance: int = 0,
    descriptor: str | None = None,
    recording_id: str | None = None,
    progress: Progress | None = None,
) -> Playback:
    """Places, the database's thresholds and the recording (``save_traversal``) of a loaded dataset.

    Args:
        descriptors: ``(n_images, D)`` of ``dataset``.
        spec: group/step (``None`` for a prepared-places dataset).
        out: the ``.rrd`` to write; default a new file in ``playback_dir()``.
    """
    database = _traversal_choice(database, queries)
    for name in (*database, queries):
        dataset.traversal_index(name)
    check_record_options(dataset, k=k, tolerance=tolerance)
    rid = recording_id or uuid.uuid4().hex
    out = check_output(out if out is not None else playback_dir() / f"{rid}.rrd")
    places = make_places(dataset, spec)
    model = fit_database(descriptors, dataset, places, database)
    return save_traversal(out, dataset, places, descriptors, model, queries, serve=serve, k=k, tolerance=tolerance,
                          descriptor=descriptor, recording_id=rid, progress=progress)


def record_dataset(
    source: str | Path,
    spec: PlaceSpec | None,
    descriptor: str,
    *,
    database: Sequence[str],
    queries: str,
    out: str | Path | None = None,
    serve: bool = False,
    k: float = 0.0,
    tolerance: int = 0,
    recording_id: str | None = None,
    cache_root: Path | None = None,
    extract_progress: Progress | None = None,
    progress: Progress | None = None,
    dtype: str = "float32",
    descriptors_file: Path | None = None,
    names_file: Path | None = None,
) -> Playback:
    """Everything from a dataset path (or ``"demo"``) to a recorded ``.rrd`` (``record_playback``).

    The output path is checked first, before any descriptor is computed. ``dtype`` is the
    descriptors' precision (``pipeline.dataset_descriptors``). With ``descriptors_file``,
    descriptors computed elsewhere (for the whole dataset) are read from it instead.
    """
    rid = recording_id or uuid.uuid4().hex
    out = check_output(out if out is not None else playback_dir() / f"{rid}.rrd")
    if descriptors_file is None:
        check_cache_root(cache_root)  # an unusable cache folder fails before the dataset is read or the demo drawn
    dataset = load_traversals(source, database, queries)
    check_record_options(dataset, k=k, tolerance=tolerance)
    make_places(dataset, spec)  # group/step that leave too few places fail before any descriptor is computed

    from vpr_explorer.pipeline import dataset_descriptors, imported_descriptors, resolve_dataset

    if descriptors_file is not None:  # the file covers the whole dataset: take the recorded traversals' rows
        full = resolve_dataset(source)
        imp = imported_descriptors(full, descriptors_file, names_file=names_file, dtype=dtype)
        row = {p: i for i, p in enumerate(full.image_paths)}
        descriptors, descriptor = imp.descriptors[[row[p] for p in dataset.image_paths]], imp.name
    else:
        descriptors = dataset_descriptors(dataset, descriptor, cache_root=cache_root, progress=extract_progress,
                                          dtype=dtype)
    return record_playback(dataset, descriptors, spec, database=database, queries=queries, out=out, serve=serve, k=k,
                           tolerance=tolerance, descriptor=descriptor, recording_id=rid, progress=progress)
