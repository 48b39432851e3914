"""A torch.hub model and a VPR-methods-evaluation run wherever a descriptor is named, and VME's recall count.

* ``hub:DIR[:ENTRY]`` with its ``--hub-*`` flags reaches every command that reads
  descriptors (``evaluate``, ``sweep``, ``acceptance``, ``failures``, ``record``, ``bench``):
  each finds the vectors ``extract`` cached under the same options (the model's forward
  passes are logged by the repository written here, so a recomputation shows), and a flag
  beside another descriptor is refused by name. A settings-file table ``model = "hub:..."``
  names the same model once: listed, extracted by that name into the same cache, chosen in
  the app's descriptor list. A link naming ``hub:...`` never runs a repository's code.
* A VME run folder is a descriptor source of ``vpr-explorer app --descriptors`` and of
  ``bench --descriptors-file``.
* ``evaluate`` prints R@1/5/10 over every query, as VME counts them, where some queries have
  no positive: checked on a hand-computed case and against VME's loop (``test_vme_run``)
  on GardensPoint frames laid out as VME's database/queries folders.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from streamlit.testing.v1 import AppTest

# the autouse fixtures of test_app (fresh caches, navigation mode) apply here too
from test_app import assert_clean, fresh_caches, navigation_mode  # noqa: F401
from cli_run import assert_one_error_line, refused, run
from test_vme_run import (RUN, descriptor_of, hand_dataset, vme_images, vme_positives, vme_recall, vme_utm,
                          write_run)
from vpr_explorer.app import DESCRIPTORS_ENV, ENTRY, descriptor_files
from vpr_explorer.app.launch import plan
from vpr_explorer.cli import main
from vpr_explorer.data.example_layouts import utm_name
from vpr_explorer.descriptors import DescriptorCache, extractor_names, get_extractor
from vpr_explorer.descriptors.custom import HubSetting, read_settings
from vpr_explorer.descriptors.registry import cache_name
from vpr_explorer.errors import VPRInputError
from vpr_explorer.pipeline import dataset_descriptors, evaluate_retrieval, open_dataset, resolve_dataset
from vpr_explorer.protocols.evaluation import recall_over_every_query
from vpr_explorer.views.report import every_query_line

AUTOUSE = (fresh_caches, navigation_mode)
TIMEOUT = 180
SIZE = ("64", "64")

# A strided convolution that logs every forward pass: "probe" for the all-zero batch the
# extractor sends once when it is built, else the number of images.
LOGGING_HUBCONF = '''
dependencies = ["torch"]

import torch


class LoggedConv(torch.nn.Module):
    def __init__(self, log, width):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, width, 3, stride=2)
        self.log = log

    def forward(self, x):
        if self.log:
            with open(self.log, "a") as fh:
                fh.write("probe\\n" if float(x.abs().sum()) == 0.0 else f"{x.shape[0]}\\n")
        return self.conv(x).mean(dim=(2, 3))


def logged_conv(log: str = "", width: int = 8):
    torch.manual_seed(0)
    return LoggedConv(log, width)
'''


def write_repo(folder: Path, hubconf: str) -> Path:
    folder.mkdir(parents=True)
    (folder / "hubconf.py").write_text(textwrap.dedent(hubconf))
    return folder


def images_computed(log: Path) -> int:
    """Images the logged model ran on (probes left out); 0 when it never ran."""
    if not log.exists():
        return 0
    return sum(int(line) for line in log.read_text().split() if line != "probe")


def cache_files(prefix: str) -> set[tuple[str, int]]:
    """The cache's files under the key folders of ``prefix`` (``hub.<folder>.<entry>``), with their mtimes."""
    folder = DescriptorCache(None).folder
    return {(str(p.relative_to(folder)), p.stat().st_mtime_ns) for d in folder.glob(f"{prefix}-*") for p in d.rglob("*")
            if p.is_file()}


@pytest.fixture(scope="module")
def hub_repo(tmp_path_factory) -> tuple[str, Path, Path]:
    """``(descriptor, repository, log)``: the logging repository, its cache filled by ``extract`` on the demo route
    with ``--hub-size 64 64`` and ``--hub-arg log=LOG``."""
    root = tmp_path_factory.mktemp("hubrepos")
    repo = write_repo(root / "logged", LOGGING_HUBCONF)
    log = root / "forward.log"
    descriptor = f"hub:{repo}:logged_conv"
    r = run("extract", "--dataset", "demo", "--descriptor", descriptor, "--hub-arg", f"log={log}", "--hub-size", *SIZE,
            timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    n = resolve_dataset("demo").n_images
    assert r.stdout.strip().splitlines()[-1].startswith(f"{n} images: 0 already cached, {n} computed locally")
    assert images_computed(log) == n
    return descriptor, repo, log


def hub_flags(log: Path) -> list[str]:
    return ["--hub-arg", f"log={log}", "--hub-size", *SIZE]


# --------------------------------------------------------------------------- every command finds extract's vectors


def test_evaluate_reads_what_extract_cached_and_other_options_are_another_key(hub_repo, tmp_path):
    descriptor, repo, log = hub_repo
    prefix = cache_name(descriptor)
    assert prefix == "hub.logged.logged_conv"
    before = cache_files(prefix)
    assert len({f.split("/")[0] for f, _ in before}) == 1  # one cache key: extract's
    log.write_text("")
    out = tmp_path / "ev.json"
    r = run("evaluate", "--dataset", "demo", "--descriptor", descriptor, *hub_flags(log), "--runs", "2",
            "--json", str(out), timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert images_computed(log) == 0 and "probe" in log.read_text()  # the model was built, never fed an image
    assert cache_files(prefix) == before  # not a file written or rewritten
    data = json.loads(out.read_text())
    assert data["settings"]["descriptor"] == descriptor

    # the same evaluation from the cached vectors, read in this process, is the command's
    from vpr_explorer.method.places import PlaceSpec
    from vpr_explorer.pipeline import evaluate_dataset

    ev = evaluate_dataset("demo", PlaceSpec(3, 10), descriptor, "paper", runs=2,
                          descriptor_options={"hub_args": (f"log={log}",), "input_size": (64, 64)})
    assert images_computed(log) == 0
    assert {m["key"]: m["recall"] for m in data["methods"]} == {
        r.key: {str(k): {"mean": v[0], "std": v[1]} for k, v in r.recall.items()} for r in ev.rows}

    # another input size is another key: computed afresh, beside extract's
    r = run("evaluate", "--dataset", "demo", "--descriptor", descriptor, "--hub-arg", f"log={log}", "--hub-size",
            "64", "48", "--runs", "2", timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert images_computed(log) == resolve_dataset("demo").n_images
    assert len({f.split("/")[0] for f, _ in cache_files(prefix)}) == 2


COMMANDS = {
    "sweep": ["--groups", "3", "--steps", "10", "--no-pr"],
    "acceptance": [],
    "failures": ["--out", "{tmp}/failures", "--limit", "2"],
    "record": ["--out", "{tmp}/run.rrd"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_takes_the_hub_flags_and_finds_the_cache(hub_repo, tmp_path, command, capsys):
    descriptor, repo, log = hub_repo
    before = cache_files(cache_name(descriptor))
    log.write_text("")
    extra = [a.format(tmp=tmp_path) for a in COMMANDS[command]]
    code = main([command, "--dataset", "demo", "--descriptor", descriptor, *hub_flags(log), *extra])
    out, err = capsys.readouterr()
    assert code == 0, err[-2000:]
    assert images_computed(log) == 0
    assert cache_files(cache_name(descriptor)) == before

    # beside a descriptor that is not hub:..., the flags are refused by name, before anything is read
    (tmp_path / "refused").mkdir()
    extra = [a.format(tmp=tmp_path / "refused") for a in COMMANDS[command]]
    assert_one_error_line(refused(capsys, command, "--dataset", "demo", "--descriptor", "pixels", "--hub-size", *SIZE,
                                  *extra), "--hub-size apply to --descriptor hub:DIR[:ENTRY] only",
                          "--descriptor pixels")
    assert_one_error_line(refused(capsys, command, "--dataset", "demo", "--hub-arg", "a=1", *extra),
                          "--hub-arg apply to --descriptor hub:DIR[:ENTRY] only", "default --descriptor")


def test_without_its_size_a_hub_model_is_refused_in_evaluate_too(hub_repo, capsys):
    descriptor, repo, log = hub_repo
    assert_one_error_line(refused(capsys, "evaluate", "--dataset", "demo", "--descriptor", descriptor),
                          "logged_conv() of", "is not one of the known models", "--hub-size W H", alone=False)


def test_bench_runs_a_hub_model_with_its_flags_and_writes_them_into_the_cells_command(hub_repo, tmp_path, capsys):
    descriptor, repo, log = hub_repo
    log.write_text("")
    out = tmp_path / "bench"
    code = main(["bench", "--datasets", "demo", "--descriptors", "pixels", descriptor, *hub_flags(log), "--runs", "1",
                 "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err[-2000:]
    assert images_computed(log) == 0
    data = json.loads((out / "bench.json").read_text())
    n = resolve_dataset("demo").n_images
    step = next(d for d in data["descriptors"] if d["descriptor"] == descriptor)
    assert step["cached_images"] == n and step["error"] is None
    assert data["settings"]["descriptor_options"] == {"hub_args": [f"log={log}"], "input_size": [64, 64]}
    cell = next(c for c in data["cells"] if c["descriptor"] == descriptor)
    assert f"--descriptor {descriptor} --hub-arg log={log} --hub-size 64 64" in cell["evaluate"]
    pixels = next(c for c in data["cells"] if c["descriptor"] == "pixels")
    assert "--hub" not in pixels["evaluate"]

    assert_one_error_line(refused(capsys, "bench", "--datasets", "demo", "--descriptors", "pixels", "--hub-size",
                                  *SIZE, "--out", str(tmp_path / "b2")),
                          "--hub-size apply to hub:DIR[:ENTRY] descriptors only", "--descriptors pixels")


# --------------------------------------------------------------------------- the settings file names a hub model


def settings_file(folder: Path, log: Path, body: str | None = None) -> Path:
    """``models.toml`` beside the repository, naming it by a relative path."""
    path = folder / "models.toml"
    path.write_text(body if body is not None else textwrap.dedent(f'''
        [models.tinyhub]
        model = "hub:logged:logged_conv"
        hub_args = {{ log = "{log}" }}
        input_size = [64, 64]
    '''))
    return path


def test_a_settings_file_hub_model_is_listed_and_extracts_into_the_same_cache(hub_repo, monkeypatch):
    descriptor, repo, log = hub_repo
    monkeypatch.setenv("VPR_EXPLORER_MODELS", str(settings_file(repo.parent, log)))
    assert "tinyhub" in extractor_names()
    spec = read_settings(repo.parent / "models.toml")["tinyhub"]
    assert spec == HubSetting("tinyhub", f"hub:{repo}:logged_conv",
                              (("hub_args", (("log", str(log)),)), ("input_size", (64, 64))))
    assert cache_name("tinyhub") == cache_name(descriptor) == "hub.logged.logged_conv"
    by_name = get_extractor("tinyhub")
    assert by_name.cache_key == get_extractor(descriptor, hub_args=(f"log={log}",), input_size=(64, 64)).cache_key
    log.write_text("")
    demo = resolve_dataset("demo")
    d = dataset_descriptors(demo, "tinyhub")
    assert images_computed(log) == 0  # extract's vectors, by the settings file's name
    np.testing.assert_array_equal(d, dataset_descriptors(demo, descriptor,
                                                         options={"hub_args": (f"log={log}",), "input_size": (64, 64)}))
    # the runtime options still apply; the hub options are the file's
    assert get_extractor("tinyhub", device="cpu").cache_key == by_name.cache_key
    with pytest.raises(VPRInputError, match="has no option input_size"):
        get_extractor("tinyhub", input_size=(32, 32))


@pytest.mark.parametrize("body, says", [
    ('[models.h]\nmodel = "hub:x"\ndim = 8\n', "has field(s) dim that a hub: model does not take"),
    ('[models.h]\nmodel = "hub:x"\nhub_args = "a=1"\n', "hub_args='a=1': give a table"),
    ('[models.h]\nmodel = "hub:x"\nhub_args = { a = [1, 2] }\n', "a value must be None, a bool, a number or a string"),
    ('[models.h]\nmodel = "hub:x"\ninput_size = 64\nshort_side = 64\n', "gives input_size and short_side"),
    ('[models.h]\nmodel = "hub:x"\nshort_side = 2\n', "short_side=2: must be a whole number of pixels"),
    ('[models.h]\nmodel = "hub:x"\nnormalisation = "zscore"\n', "normalisation='zscore': choose one of"),
    ('[models.h]\nmodel = "hub:"\n', "give hub:DIR or hub:DIR:ENTRY"),
])
def test_a_bad_hub_table_is_refused_naming_the_file_and_table(tmp_path, body, says):
    path = tmp_path / "models.toml"
    path.write_text(body)
    with pytest.raises(VPRInputError) as err:
        read_settings(path)
    assert f"{path}: [models.h]" in str(err.value) and says in str(err.value)


def test_a_settings_hub_model_reads_home_and_absolute_folders_and_its_missing_folder_is_unavailable(tmp_path,
                                                                                                     monkeypatch):
    from vpr_explorer.descriptors import available_extractors

    monkeypatch.setenv("HOME", str(tmp_path))
    path = settings_file(tmp_path, tmp_path / "log", '[models.home]\nmodel = "hub:~/repo"\nshort_side = 100\n'
                                                     f'[models.abs]\nmodel = "hub:{tmp_path}/gone:entry"\n')
    models = read_settings(path)
    assert models["home"] == HubSetting("home", f"hub:{tmp_path / 'repo'}", (("short_side", 100),))
    assert models["abs"].descriptor == f"hub:{tmp_path / 'gone'}:entry"
    monkeypatch.setenv("VPR_EXPLORER_MODELS", str(path))
    reasons = available_extractors()
    assert "is not a folder" in reasons["abs"] and "pixels" in reasons
    with pytest.raises(VPRInputError, match="is unavailable here"):
        get_extractor("abs")


def test_the_app_lists_the_settings_hub_model_and_computes_with_it(hub_repo, monkeypatch):
    descriptor, repo, log = hub_repo
    monkeypatch.setenv("VPR_EXPLORER_MODELS", str(settings_file(repo.parent, log)))
    log.write_text("")
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.run()
    assert_clean(at)
    radio = at.radio(key="w_descriptor")
    assert "tinyhub" in radio.options
    radio.set_value("tinyhub").run()
    assert_clean(at)
    assert at.session_state["view"].descriptor == "tinyhub" and at.query_params["descriptor"] == "tinyhub"
    n = resolve_dataset("demo").n_images
    assert any(f"tinyhub descriptors ready: {n} × 8" in s.value for s in at.success), [s.value for s in at.success]
    assert images_computed(log) == 0  # extract's vectors


def test_a_link_naming_a_hub_folder_runs_nothing_of_it(tmp_path):
    """A folder named like MegaLoc (a known model: no size needed), whose hubconf leaves a mark when it runs."""
    mark = tmp_path / "ran"
    repo = write_repo(tmp_path / "gmberton_MegaLoc_main",
                      f'import pathlib\npathlib.Path("{mark}").write_text("ran")\n\n'
                      "def get_trained_model():\n    import torch\n    return torch.nn.Flatten()\n")
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.query_params.update(source="demo", descriptor=f"hub:{repo}")
    at.run()
    assert_clean(at)
    assert any(f"descriptor='hub:{repo}'" in w.value and "a link never does" in w.value for w in at.warning)
    assert not mark.exists()


# --------------------------------------------------------------------------- VME run folders: app --descriptors, bench


@pytest.fixture
def small_run(tmp_path):
    """``(dataset, run folder)``: test_vme_run's small dataset and its run (each image's own vector)."""
    from test_vme_run import write_small

    ds = open_dataset(write_small(tmp_path / "data" / "small"))
    d = np.stack([descriptor_of(p.name) for p in ds.image_paths])
    return ds, write_run(tmp_path / "data" / "logs" / "default" / RUN, ds, d)


def test_app_launch_takes_a_run_folder_and_the_session_opens_it(small_run, monkeypatch):
    ds, logdir = small_run
    launch = plan(dataset=str(ds.root), descriptors=logdir)
    assert launch.env[DESCRIPTORS_ENV] == str(logdir.resolve())
    assert f"descriptor={RUN}" in launch.url
    assert descriptor_files(launch.env) == {RUN: logdir.resolve()}
    for name, value in launch.env.items():
        monkeypatch.setenv(name, value)
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT)
    at.run()
    assert_clean(at)
    assert at.session_state["view"].descriptor == RUN
    assert any(f"{RUN} descriptors ready: 60 × 16" in s.value for s in at.success), [s.value for s in at.success]

    (logdir / "queries_descriptors.npy").unlink()
    with pytest.raises(VPRInputError, match="queries_descriptors.npy: missing"):
        plan(dataset=str(ds.root), descriptors=logdir)
    with pytest.raises(VPRInputError, match="no such file; give a .npz, .npy or hloc .h5 file, or a"):
        plan(dataset=str(ds.root), descriptors=logdir.parent / "gone.npy")


def test_bench_reads_a_run_folder_as_evaluate_does(small_run, tmp_path, capsys):
    ds, logdir = small_run
    out = tmp_path / "bench"
    code = main(["bench", "--datasets", str(ds.root), "--descriptors-file", f"{ds.root}={logdir}", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err[-2000:]
    data = json.loads((out / "bench.json").read_text())
    (cell,) = data["cells"]
    assert cell["descriptor"] == RUN and cell["error"] is None
    assert f"--descriptors {logdir}" in cell["evaluate"]
    step = data["descriptors"][0]
    assert step["descriptors_file"] == str(logdir) and len(step["queries_descriptors_sha256"]) == 64
    image = next(m for m in cell["evaluation"]["methods"] if m["key"] == "image-baseline")
    want = vme_recall(logdir, ds.root / "database", ds.root / "queries")  # every query has a positive here
    assert {k: image["recall"][str(k)]["mean"] for k in (1, 5, 10)} == pytest.approx(want, abs=1e-12)
    assert cell["evaluation"]["recall_over_every_query"] == {str(k): image["recall"][str(k)]["mean"]
                                                             for k in (1, 5, 10)}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_other_commands_read_a_run_folder_as_their_descriptors(small_run, tmp_path, command, capsys):
    ds, logdir = small_run
    extra = [a.format(tmp=tmp_path) for a in COMMANDS[command]]
    code = main([command, "--dataset", str(ds.root), "--descriptors", str(logdir), *extra])
    out, err = capsys.readouterr()
    assert code == 0, err[-2000:]
    assert RUN in out if command != "record" else (tmp_path / "run.rrd").stat().st_size > 0


# --------------------------------------------------------------------------- R@K over every query, as VME counts


@pytest.mark.parametrize("nearest, want", [(1, 0.5), (0, 0.0)])
def test_evaluate_prints_recall_over_every_query_on_a_hand_computed_case(tmp_path, nearest, want):
    """Query 0's nearest descriptor is database image ``nearest`` and its second database image 1 or 0: with
    ``nearest = 1`` it is a hit at 1, 5, 10: VME 1/2 = 50 %, the table 1/1; with ``nearest = 0`` it is a hit at
    5 and 10 only (image 1 second): R@1 0/2, R@5 = R@10 1/2."""
    root = hand_dataset(tmp_path / "hand")
    ds = open_dataset(root)
    eye = np.eye(4, dtype=np.float32)
    q0 = eye[nearest] + 0.1 * eye[1 - nearest]
    q = np.array([q0, eye[3] + 0.2 * eye[2]], dtype=np.float32)
    logdir = write_run(tmp_path / "logs" / RUN, ds, np.vstack([eye, q / np.linalg.norm(q, axis=1, keepdims=True)]))
    vme = vme_recall(logdir, root / "database", root / "queries")
    assert vme == {1: want, 5: 0.5, 10: 0.5}
    out = tmp_path / "r.json"
    r = run("evaluate", "--dataset", str(root), "--descriptors", str(logdir), "--geometry", "frames", "--group", "1",
            "--step", "1", "--json", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    rates = " / ".join(f"{100 * vme[k]:.1f}" for k in (1, 5, 10))
    assert (f"R@1/5/10 over every query, as VPR-methods-evaluation counts them: {rates} % (2 queries, 1 of them "
            "without a positive)") in r.stdout.splitlines()
    data = json.loads(out.read_text())
    assert data["recall_over_every_query"] == {str(k): v for k, v in vme.items()}
    image = next(m for m in data["methods"] if m["key"] == "image-baseline")
    assert image["recall"]["1"]["mean"] == 2 * want and image["recall"]["10"]["mean"] == 1.0  # over 1 query


def test_no_line_when_every_query_has_a_positive_and_none_for_aligned_protocols(small_run):
    ds, logdir = small_run
    from vpr_explorer.pipeline import imported_descriptors
    from vpr_explorer.method.places import PlaceSpec

    ev = evaluate_retrieval(ds, imported_descriptors(ds, logdir).descriptors, spec=PlaceSpec(3, 10))
    assert ev.settings["queries_without_positive"] == 0 and every_query_line(ev) is None
    assert recall_over_every_query(ev) == {k: ev.row("image-baseline").recall[k][0] for k in (1, 5, 10)}
    from vpr_explorer.pipeline import evaluate_dataset

    assert recall_over_every_query(evaluate_dataset("demo", PlaceSpec(3, 10), "pixels", "traversal")) is None


@pytest.mark.realdata
def test_recall_over_every_query_equals_vmes_loop_on_gardens_point(tmp_path, data_root):
    """GardensPoint day_right as the database along a line, night_right as queries 15 m off it; the last 60
    queries lie 500 m off (no database image within 25 m): VME's loop over every query against the printed line."""
    gp = data_root / "GardensPointWalking"
    root = tmp_path / "gp"
    for f in range(200):
        for side, trav, north in (("database", "day_right", 6960000.0),
                                  ("queries", "night_right", 6960015.0 if f < 140 else 6960500.0)):
            link = root / side / ("seq2" if f < 100 else "seq10") / utm_name(500000 + 10.0 * f, north, f)
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to((gp / trav / f"Image{f:03d}.jpg").resolve())
    ds = open_dataset(root)
    logdir = write_run(tmp_path / "logs" / RUN, ds, np.asarray(dataset_descriptors(ds, "pixels")))
    positives = vme_positives(vme_utm(vme_images(root / "database")), vme_utm(vme_images(root / "queries")))
    assert sum(not p for p in positives) == 60
    want = vme_recall(logdir, root / "database", root / "queries")
    assert 0.05 < want[1] < 0.65  # neither nothing nor everything of the 140 that can hit

    out = tmp_path / "r.json"
    r = run("evaluate", "--dataset", str(root), "--descriptors", str(logdir), "--json", str(out), timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads(out.read_text())
    assert {int(k): v for k, v in got["recall_over_every_query"].items()} == pytest.approx(want, abs=1e-12)
    line = next(x for x in r.stdout.splitlines() if x.startswith("R@1/5/10 over every query"))
    assert line.endswith("% (200 queries, 60 of them without a positive)")
    assert " / ".join(f"{100 * want[k]:.1f}" for k in (1, 5, 10)) in line
    image = next(m for m in got["methods"] if m["key"] == "image-baseline")
    assert image["recall"]["1"]["mean"] == pytest.approx(want[1] * 200 / 140, abs=1e-12)  # the table: over 140
