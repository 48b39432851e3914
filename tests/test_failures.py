"""``views.failures`` and ``vpr-explorer failures``: the failing queries, their pictures, the index and the CSV.

GardensPoint Walking: night_right queries against the day_right database, pixel descriptors,
group 3, step 10. The failing queries and their kinds are checked against a plain loop over
``explain_query`` written from the definition (the module doc's table); the pictures by their
size, their tiles and the colour of each frame; the index and the CSV by reading them back.
The database/queries layout is GardensPoint written by ``data.example_layouts`` (the same
images, right within ±2 frames); bad input runs on the built-in demo route.
"""

from __future__ import annotations

import csv
import re

import numpy as np
import pytest
from PIL import Image

from tests.cli_run import assert_one_error_line, refused
from vpr_explorer.cli import failures as cli
from vpr_explorer.cli import main
from vpr_explorer.data.aligned import database_queries
from vpr_explorer.errors import VPRInputError
from vpr_explorer.method.places import PlaceGeometry, PlaceSpec
from vpr_explorer.method.retrieval import decide
from vpr_explorer.pipeline import dataset_descriptors
from vpr_explorer.views import failures as vf
from vpr_explorer.views.numbers import RetrievalPlaces, explain_query, fit_retrieval

METHODS = ("raw-weighted", "margin-weighted", "place-baseline", "image-baseline", "global-auto")
GP_PAIR = ("--queries", "night_right", "--database", "day_right", "--descriptor", "pixels")


def fitted_gp(gardens_point, tolerance: int):
    value = database_queries(gardens_point, "night_right", database=["day_right"], tolerance=tolerance)
    desc = dataset_descriptors(value, "pixels")
    return fit_retrieval(desc, value, RetrievalPlaces(PlaceGeometry.FRAMES, PlaceSpec(3, 10))), desc


@pytest.fixture(scope="module")
def gp0(gardens_point):
    """GardensPoint night_right against day_right, the same frame right."""
    return fitted_gp(gardens_point, 0)


@pytest.fixture(scope="module")
def gp2(gardens_point):
    """GardensPoint night_right against day_right, ±2 frames right."""
    return fitted_gp(gardens_point, 2)


def reference_kinds(fitted, desc, key: str, user_theta: float | None = None) -> dict[int, str]:
    """query -> kind, from ``explain_query`` one query at a time and the definition."""
    out = {}
    for q in range(fitted.dataset.n_queries):
        d = explain_query(fitted, desc, q, user_theta=user_theta)
        o = d.outcomes[key]
        accepted = o.answer_place[0] >= 0
        has_right_place = len(d.true_places) > 0
        no_positive = len(fitted.dataset.ground_truth.positives(q)) == 0
        if has_right_place and not accepted:
            out[q] = "wrong-reject"
        elif has_right_place and o.rank[0] != 1:
            out[q] = "wrong-answer"
        elif no_positive and accepted:
            out[q] = "accepted-unknown"
    return out


def frame_colours(picture: Image.Image, i: int) -> set[tuple[int, int, int]]:
    """The colours at the middle of each side of tile ``i``'s frame."""
    x0, y0, x1, y1 = vf.tile_box(i)
    half = vf.BORDER // 2
    mx, my = (x0 + x1) // 2, (y0 + y1) // 2
    return {picture.getpixel(p) for p in ((x0 + half, my), (x1 - 1 - half, my), (mx, y0 + half), (mx, y1 - 1 - half))}


def tiles_on_line(picture: Image.Image, y: int) -> int:
    """How many runs of non-white pixels a row of the picture crosses (the frames' top edges at ``y``)."""
    row = np.asarray(picture)[y]
    ink = ~(row == 255).all(axis=1)
    return int(np.count_nonzero(ink[1:] & ~ink[:-1]) + ink[0])


# --------------------------------------------------------------------------- which queries fail


@pytest.mark.parametrize("key", METHODS)
@pytest.mark.parametrize("tolerance", [0, 2])
def test_failing_queries_are_the_plain_loops(gp0, gp2, key, tolerance):
    fitted, desc = gp0 if tolerance == 0 else gp2
    want = reference_kinds(fitted, desc, key)
    result = vf.find_failures(fitted, desc, key)
    assert {f.query: f.kind.value for f in result.failures} == want
    assert result.failing.tolist() == sorted(want)
    assert {k.value: n for k, n in result.counts.items()} == {
        k.value: sum(v == k.value for v in want.values()) for k in vf.FailureKind}
    assert result.left_out == 0 and result.notes == ()
    assert result.n_known + result.n_unknown + result.n_between == fitted.dataset.n_queries
    assert want, "GardensPoint night against day with pixels fails some queries under every method"


def test_failure_records_follow_the_explained_decision(gp2):
    fitted, desc = gp2
    result = vf.find_failures(fitted, desc, "raw-weighted", top=4)
    for f in result.failures:
        d = explain_query(fitted, desc, f.query)
        o = d.outcomes["raw-weighted"]
        true = d.true_places[np.argmax(d.raw[d.true_places])]
        assert f.true_place == true and f.true_rank == o.rank[0]
        assert f.true_image == fitted.model.images[d.best_image[true]]
        assert f.answer_place == o.answer_place[0]
        theta = d.thresholds["weighted"]
        if f.kind is vf.FailureKind.WRONG_ANSWER:
            assert f.reason.startswith(f"accepted as place {f.answer_place} (wrong)")
            assert f.top_place == f.answer_place and f.score == d.raw[f.answer_place]
        else:
            assert f.reason.startswith("rejected") and f.answer_image == -1
            assert f.top_place == np.argmax(d.raw)  # the raw rule's closest place: the best raw_p
        assert f.margin == pytest.approx(f.score - theta[f.top_place], abs=1e-12)
        assert len(f.tiles) == 1 + 4 + 1
        assert f.tiles[0].right is None and f.tiles[-1].right is True


def test_ranked_candidates_hand_cases():
    # four places of one image each: raw_p = the image's score
    sims = np.array([0.9, 0.5, 0.7, 0.3])
    theta = np.array([0.95, 0.45, 0.6, 0.1])  # margins −0.05, +0.05, +0.10, +0.20: place 0 dropped
    d = decide(sims, np.arange(4), 4, {"weighted": theta, "simple": theta}, [1])
    # raw rule: kept by raw_p (answer 2 first), then the dropped place 0
    assert vf.ranked_candidates(d, "raw-weighted", 4) == [(2, 1), (1, 2), (3, 3), (0, None)]
    assert vf.ranked_candidates(d, "raw-weighted", 2) == [(2, 1), (1, 2)]
    # margin rule: kept by margin
    assert vf.ranked_candidates(d, "margin-weighted", 4) == [(3, 1), (2, 2), (1, 3), (0, None)]
    # no threshold: every place kept, by raw_p; the image level ranks images
    assert vf.ranked_candidates(d, "place-baseline", 3) == [(0, 1), (2, 2), (1, 3)]
    assert vf.ranked_candidates(d, "image-baseline", 2) == [(0, 1), (2, 2)]
    # every place below its θ: rejected, the closest places by raw_p (raw rule) or by margin
    high = np.array([0.95, 0.8, 0.72, 0.5])  # margins −0.05, −0.30, −0.02, −0.20
    r = decide(sims, np.arange(4), 4, {"weighted": high, "simple": high}, [1])
    assert r.answer("raw-weighted") == -1
    assert vf.ranked_candidates(r, "raw-weighted", 4) == [(0, None), (2, None), (1, None), (3, None)]
    assert vf.ranked_candidates(r, "margin-weighted", 4) == [(2, None), (0, None), (3, None), (1, None)]
    # an exact tie on the ranking score goes to the lower index
    tie = decide(np.array([0.5, 0.7, 0.7]), np.arange(3), 3, {"weighted": np.zeros(3), "simple": np.zeros(3)}, [0])
    assert vf.ranked_candidates(tie, "raw-weighted", 3) == [(1, 1), (2, 2), (0, 3)]


def test_failure_kinds_by_the_table():
    known = np.array([1, 1, 1, 0, 0, 0], dtype=bool)
    unknown = np.array([0, 0, 0, 1, 1, 0], dtype=bool)  # the last: positives between places only
    accepted = np.array([1, 1, 0, 1, 0, 1], dtype=bool)
    right = np.array([1, 0, 0, 0, 0, 0], dtype=bool)
    assert vf.failure_kinds(known, unknown, accepted, right).tolist() == [
        "", "wrong-answer", "wrong-reject", "accepted-unknown", "", ""]


def test_bad_arguments_are_refused_by_name(gp0):
    fitted, desc = gp0
    for kwargs, fragment in (({"top": 0}, "top=0"), ({"limit": -1}, "limit=-1"), ({"kinds": ("wrong",)}, "kinds=")):
        with pytest.raises(VPRInputError, match=re.escape(fragment)):
            vf.find_failures(fitted, desc, "raw-weighted", **kwargs)
    with pytest.raises(VPRInputError, match="global-user"):
        vf.find_failures(fitted, desc, "global-user")
    with pytest.raises(VPRInputError, match="global-oracle"):
        vf.find_failures(fitted, desc, "global-oracle")


# --------------------------------------------------------------------------- the command's files


@pytest.fixture(scope="module")
def gp_out(gardens_point, tmp_path_factory):
    """``vpr-explorer failures`` on GardensPoint, raw-weighted, three candidates: (folder, stdout)."""
    out = tmp_path_factory.mktemp("failures") / "gp"
    code = main(["failures", "--dataset", str(gardens_point.root), *GP_PAIR, "--method", "raw-weighted", "--top", "3",
                 "--out", str(out)])
    return out, code


def test_one_png_per_failure_with_its_tiles_and_frames(gp0, gp_out):
    fitted, desc = gp0
    out, code = gp_out
    assert code == 0
    want = reference_kinds(fitted, desc, "raw-weighted")
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert pngs == sorted(cli.png_name(q, kind, fitted.dataset.n_queries) for q, kind in want.items())
    assert sorted(p.name for p in out.iterdir()) == sorted([*pngs, "failures.csv", "index.html"])
    n_tiles = 1 + 3 + 1
    width = 2 * vf.MARGIN + n_tiles * (vf.TILE_W + 2 * vf.BORDER) + (n_tiles - 1) * vf.GAP
    colours = set()
    drawn = {f.query: f for f in vf.find_failures(fitted, desc, "raw-weighted", top=3).failures}
    for name in pngs:
        q = int(name.split("-")[0])
        with Image.open(out / name) as im:
            picture = im.convert("RGB")
            assert im.format == "PNG"
        assert picture.size == vf.grid_size(n_tiles) and picture.width == width
        assert tiles_on_line(picture, vf.tile_box(0)[1] + 1) == n_tiles
        d = explain_query(fitted, desc, q)
        right_places = set(d.true_places.tolist())
        failure = drawn[q]
        assert frame_colours(picture, 0) == {vf.GREY}
        for i, tile in enumerate(failure.tiles[1:], start=1):
            place = int(re.search(r"place (\d+)", tile.caption[0]).group(1))
            colour = vf.GREEN if place in right_places else vf.RED
            assert frame_colours(picture, i) == {colour}, (name, i, tile.caption)
            colours.add(colour)
        assert failure.tiles[-1].caption[0].startswith("true match")
        assert frame_colours(picture, n_tiles - 1) == {vf.GREEN}
    assert colours == {vf.GREEN, vf.RED}


def test_index_and_csv_list_every_png(gp0, gp_out):
    fitted, desc = gp0
    out, _ = gp_out
    pngs = sorted(p.name for p in out.glob("*.png"))
    page = (out / "index.html").read_text(encoding="utf-8")
    for name in pngs:
        assert f'<a href="{name}">' in page
    assert page.count("<tr>") == 1 + len(pngs)
    assert page.count('src="data:image/jpeg;base64,') == len(pngs)
    links = re.findall(r'(?:src|href)="([^"]+)"', page)
    assert all(link.startswith("data:image/jpeg;base64,") or link in pngs for link in links)
    assert "<script>" in page and "<link" not in page and "@import" not in page and "url(" not in page
    for setting in ("dataset", "descriptor", "method", "places", "tolerance"):
        assert f"<dt>{setting}</dt>" in page
    with (out / "failures.csv").open(newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == vf.COLUMNS
    result = vf.find_failures(fitted, desc, "raw-weighted", top=3)
    named = {f.query: cli.png_name(f.query, f.kind.value, fitted.dataset.n_queries) for f in result.failures}
    assert rows == vf.failure_rows(fitted, result.failures, named)
    assert sorted(row["png"] for row in rows) == pngs
    want = reference_kinds(fitted, desc, "raw-weighted")
    assert {int(row["query"]): row["kind"] for row in rows} == want


def test_limit_and_kind(gardens_point, gp0, tmp_path, capsys):
    fitted, desc = gp0
    want = reference_kinds(fitted, desc, "global-user", user_theta=0.15)
    rejects = sorted(q for q, k in want.items() if k == "wrong-reject")
    assert rejects and len(rejects) < len(want)
    dataset = str(gardens_point.root)
    r = refused(capsys, "failures", "--dataset", dataset, *GP_PAIR, "--method", "global-user", "--theta", "0.15",
                "--kind", "wrong-reject", "--out", str(tmp_path / "rejects"))
    assert r.returncode == 0, r.stderr
    assert sorted(int(p.name.split("-")[0]) for p in (tmp_path / "rejects").glob("*-wrong-reject.png")) == rejects
    assert len(list((tmp_path / "rejects").glob("*.png"))) == len(rejects)
    r = refused(capsys, "failures", "--dataset", dataset, *GP_PAIR, "--method", "global-user", "--theta", "0.15",
                "--limit", "5", "--out", str(tmp_path / "five"))
    assert r.returncode == 0, r.stderr
    first = sorted(want)[:5]
    assert sorted(int(p.name.split("-")[0]) for p in (tmp_path / "five").glob("*.png")) == first
    assert f"drawn: 5 of {len(want)} failures" in r.stdout and f"{len(want) - 5} left out by the limit" in r.stdout
    with (tmp_path / "five" / "failures.csv").open(newline="") as fh:
        assert [int(row["query"]) for row in csv.DictReader(fh)] == first


def test_a_non_empty_out_is_refused_unless_overwrite(gardens_point, tmp_path, capsys):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    args = ("failures", "--dataset", str(gardens_point.root), *GP_PAIR, "--limit", "2", "--out", str(out))
    assert_one_error_line(refused(capsys, *args), "--out", "not empty", "--overwrite")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    r = refused(capsys, *args, "--overwrite")
    assert r.returncode == 0, r.stderr
    assert (out / "keep.txt").read_text() == "mine" and len(list(out.glob("*.png"))) == 2


# --------------------------------------------------------------------------- other layouts


@pytest.fixture(scope="module")
def layouts(data_root, tmp_path_factory):
    """GardensPoint in each layout ``example_layouts`` writes: layout name -> path."""
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts

    return write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path_factory.mktemp("failure_layouts"))


def test_database_queries_layout_fails_the_same_queries(layouts, gp2, tmp_path, capsys):
    """database/ + queries/ with @UTM@ names 10 m apart: right within 25 m, the ±2 frames of the aligned value."""
    from vpr_explorer.pipeline import open_dataset

    fitted, desc = gp2
    want = reference_kinds(fitted, desc, "raw-weighted")
    value = open_dataset(layouts["database-queries"])
    layout_desc = dataset_descriptors(value, "pixels")
    layout_fit = fit_retrieval(layout_desc, value, RetrievalPlaces(PlaceGeometry.FRAMES, PlaceSpec(3, 10)))
    assert vf.find_failures(layout_fit, layout_desc, "raw-weighted", limit=0).failing.tolist() == sorted(want)
    out = tmp_path / "dq"
    r = refused(capsys, "failures", "--dataset", str(layouts["database-queries"]), "--descriptor", "pixels",
                "--geometry", "frames", "--top", "2", "--limit", "10", "--out", str(out))
    assert r.returncode == 0, r.stderr
    counts = {k: sum(v == k for v in want.values()) for k in ("wrong-answer", "wrong-reject")}
    assert (f"{counts['wrong-answer']} wrong answers and {counts['wrong-reject']} wrong rejects of "
            f"{fitted.right_places(np.arange(200)).any(axis=1).sum()} queries with a right place") in r.stdout
    with (out / "failures.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(int(row["query"]), row["kind"]) for row in rows] == sorted(want.items())[:10]
    assert all(re.fullmatch(r"@.*@\.jpg", row["query image"]) for row in rows)
    assert len(list(out.glob("*.png"))) == 10
    assert "<dt>layout</dt><dd>database-queries</dd>" in (out / "index.html").read_text()


def test_manifest_unknown_place_queries_accepted(layouts, tmp_path, capsys):
    """The manifest's queries without a place have no positive: the place-level baseline accepts every one."""
    out = tmp_path / "manifest"
    r = refused(capsys, "failures", "--dataset", str(layouts["manifest"]), "--descriptor", "pixels",
                "--method", "place-baseline", "--kind", "accepted-unknown", "--limit", "3", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "140 accepted of 140 unknown-place queries" in r.stdout and "137 left out by the limit" in r.stdout
    pngs = sorted(out.glob("*.png"))
    assert [p.name for p in pngs] == ["003-accepted-unknown.png", "004-accepted-unknown.png", "005-accepted-unknown.png"]
    with Image.open(pngs[0]) as im:
        picture = im.convert("RGB")
    assert frame_colours(picture, 1 + 5) == {vf.GREY}  # no true match
    assert all(frame_colours(picture, i) == {vf.RED} for i in range(1, 6))


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("args, fragments", [
    (("--top", "0"), ("--top 0",)),
    (("--limit", "-1"), ("--limit -1",)),
    (("--method", "global-oracle"), ("--method global-oracle", "global-user")),
    (("--method", "margin"), ("--method margin", "raw-weighted")),
    (("--method", "global-user"), ("--method global-user needs --theta",)),
    (("--theta", "0.5"), ("--theta applies to --method global-user",)),
    (("--method", "global-user", "--theta", "nan"), ("--theta nan",)),
    (("--tolerance", "-1"), ("--tolerance=-1",)),
])
def test_bad_options_are_one_error_line(args, fragments, tmp_path, capsys):
    r = refused(capsys, "failures", "--dataset", "demo", "--descriptor", "pixels", *args, "--out", str(tmp_path / "o"))
    assert_one_error_line(r, *fragments)
    assert not (tmp_path / "o").exists()


def test_out_a_file_is_refused(tmp_path, capsys):
    (tmp_path / "f").write_text("x")
    assert_one_error_line(refused(capsys, "failures", "--dataset", "demo", "--out", str(tmp_path / "f")),
                          "--out", "a file, not a folder")


def test_layout_refuses_tolerance_and_traversals(layouts, tmp_path, capsys):
    base = ("failures", "--dataset", str(layouts["database-queries"]), "--descriptor", "pixels", "--out",
            str(tmp_path / "o"))
    assert_one_error_line(refused(capsys, *base, "--tolerance", "2"), "--tolerance", "--radius")
    assert_one_error_line(refused(capsys, *base, "--queries", "night"), "--queries", "drop --queries")


def test_the_command_offers_the_library_s_choices():
    from vpr_explorer.method.retrieval import METHODS

    assert cli.METHOD_KEYS == tuple(m.key for m in METHODS if m.key != "global-oracle")
    assert cli.KINDS == tuple(k.value for k in vf.FailureKind)


def test_kind_choices_are_argparse_s(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["failures", "--dataset", "demo", "--kind", "wrong", "--out", "x"])
    assert exc.value.code == 2
    assert "--kind" in capsys.readouterr().err
