"""The ``--hub-*`` flags of a ``hub:DIR[:ENTRY]`` descriptor in every command's recorded settings.

``evaluate``, ``acceptance``, ``failures``, ``sweep`` and ``bench`` record the flags given as one
settings entry, right after the descriptor's name, written as they are typed
(``"hub_options": "--hub-arg width=4 --hub-size 64 48"``): two runs of the same model with
other options never record the same settings, and the entry, split as a shell splits it and
given again, is the same model (the same settings, the same numbers). Runs without the flags
record exactly what they recorded without this entry: the library's own settings. In a bench,
the cells and descriptors step of a ``hub:`` descriptor carry the entry, the others do not.

Every run is a real one of the command's ``main`` on the demo route (aligned traversals) or a
database/queries folder written here, with a tiny torch.hub repository written here too.
"""

from __future__ import annotations

import csv
import io
import json
import shlex
import textwrap
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vpr_explorer.cli import main
from vpr_explorer.cli.common import hub_options
from vpr_explorer.cli.parser import build_parser
from vpr_explorer.data.example_layouts import utm_name
from vpr_explorer.descriptors.hub import hub_arguments
from vpr_explorer.method.places import PlaceSpec
from vpr_explorer.pipeline import evaluate_dataset
from vpr_explorer.descriptors.hub import HUB_SETTING, hub_flags, hub_settings

# A strided convolution, the same weights every time it is built (``width`` channels out).
TINY_HUBCONF = '''
dependencies = ["torch"]

import torch


class Tiny(torch.nn.Module):
    def __init__(self, width):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, width, 3, stride=2)

    def forward(self, x):
        return self.conv(x).mean(dim=(2, 3))


def tiny(width: int = 8):
    torch.manual_seed(0)
    return Tiny(width)
'''

#: the flags of every hub run here, and the entry they record
FLAGS = ["--hub-arg", "width=4", "--hub-size", "64", "48"]
RECORDED = "--hub-arg width=4 --hub-size 64 48"
#: the same model with another input size: another run, other settings
OTHER_FLAGS = ["--hub-arg", "width=4", "--hub-size", "48", "48"]


@pytest.fixture(scope="module")
def descriptor(tmp_path_factory) -> str:
    """``hub:DIR:tiny``, DIR a torch.hub repository written here."""
    repo = tmp_path_factory.mktemp("hubrepos") / "tiny"
    repo.mkdir()
    (repo / "hubconf.py").write_text(textwrap.dedent(TINY_HUBCONF))
    return f"hub:{repo}:tiny"


@pytest.fixture(scope="module")
def positions(tmp_path_factory) -> Path:
    """A database/queries folder: eight database images 30 m apart along a line, three queries near three of them."""
    root = tmp_path_factory.mktemp("positions")
    rng = np.random.default_rng(0)
    for folder, easts, first in (("database", [30.0 * i for i in range(8)], 0), ("queries", [5.0, 95.0, 181.0], 100)):
        (root / folder).mkdir()
        for i, east in enumerate(easts):
            pixels = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
            Image.fromarray(pixels).save(root / folder / utm_name(500000.0 + east, 6960000.0, first + i))
    return root


def run_main(capsys, *argv: str) -> str:
    """``main(argv)`` in this process, which must exit 0; returns what it printed."""
    code = main(list(argv))
    out, err = capsys.readouterr()
    assert code == 0, err[-2000:]
    return out


def settings_of(path: Path) -> dict:
    return json.loads(path.read_text())["settings"]


def after(settings: dict, key: str) -> str | None:
    """The key that follows ``key`` in ``settings``, or None for the last."""
    keys = list(settings)
    i = keys.index(key) + 1
    return keys[i] if i < len(keys) else None


def without_hub(settings: dict) -> dict:
    return {k: v for k, v in settings.items() if k != HUB_SETTING}


# --------------------------------------------------------------------------- the entry, written and read back


def test_no_options_record_nothing():
    assert hub_flags({}) == [] and hub_settings({}) == {}
    assert hub_settings({"input_size": None, "short_side": None}) == {}


def test_each_option_is_written_as_its_flag_in_one_order():
    options = {"normalisation": "unit", "short_side": 480, "hub_args": ("a=1", "b=x y")}
    assert hub_flags(options) == ["--hub-arg", "a=1", "--hub-arg", "b=x y", "--hub-short-side", "480",
                                  "--hub-normalisation", "unit"]
    # a shell's quoting: the argument with a space stays one word
    assert hub_settings(options) == {HUB_SETTING: "--hub-arg a=1 --hub-arg 'b=x y' --hub-short-side 480 "
                                                  "--hub-normalisation unit"}
    assert hub_settings({"input_size": (64, 48)}) == {HUB_SETTING: "--hub-size 64 48"}
    assert hub_settings({"input_size": [64, 48]}) == {HUB_SETTING: "--hub-size 64 48"}


def test_pairs_and_mappings_are_written_so_that_hub_arg_reads_the_same_values_back():
    values = {"n": 3, "scale": 0.5, "tiny": 1e-5, "on": True, "off": False, "none": None, "name": "resnet",
              "digits": "1", "word_true": "true", "word_none": "None", "quoted": "'q'"}
    written = hub_flags({"hub_args": values})
    assert written[::2] == ["--hub-arg"] * len(values)
    assert written[1::2] == ["n=3", "scale=0.5", "tiny=1e-05", "on=true", "off=false", "none=None", "name=resnet",
                             "digits='1'", "word_true='true'", "word_none='None'", "quoted=''q''"]
    back = dict(hub_arguments(written[1::2]))
    assert back == values and all(type(back[k]) is type(v) for k, v in values.items())
    assert hub_flags({"hub_args": tuple(values.items())}) == written


@pytest.mark.parametrize("flags", [
    FLAGS,
    ["--hub-arg", "width=4", "--hub-arg", "label=a b", "--hub-short-side", "40", "--hub-normalisation", "signed"],
])
def test_the_recorded_entry_given_again_is_the_same_options(descriptor, flags):
    parser = build_parser()
    args = parser.parse_args(["evaluate", "--dataset", "demo", "--descriptor", descriptor, *flags])
    entry = hub_settings(hub_options(args))[HUB_SETTING]
    again = parser.parse_args(["evaluate", "--dataset", "demo", "--descriptor", descriptor, *shlex.split(entry)])
    assert hub_options(again) == hub_options(args)


# --------------------------------------------------------------------------- evaluate


def test_evaluate_records_the_flags_after_the_descriptor_and_they_repeat_the_run(descriptor, tmp_path, capsys):
    out = run_main(capsys, "evaluate", "--dataset", "demo", "--descriptor", descriptor, *FLAGS, "--runs", "2",
                   "--json", str(tmp_path / "hub.json"))
    data = json.loads((tmp_path / "hub.json").read_text())
    settings = data["settings"]
    assert settings[HUB_SETTING] == RECORDED
    assert after(settings, "descriptor") == HUB_SETTING and after(settings, HUB_SETTING) == "dtype"
    assert settings["descriptor"] == descriptor
    assert f"{HUB_SETTING}={RECORDED}" in out.splitlines()[0]  # the report's header line

    # the library's run of the same model records the same settings, the entry included
    ev = evaluate_dataset("demo", PlaceSpec(3, 10), descriptor, "paper", runs=2,
                          descriptor_options={"hub_args": ("width=4",), "input_size": (64, 48)})
    assert settings == ev.settings

    # the entry, given again as typed: the same settings and numbers
    run_main(capsys, "evaluate", "--dataset", "demo", "--descriptor", descriptor, *shlex.split(RECORDED),
             "--runs", "2", "--json", str(tmp_path / "again.json"))
    again = json.loads((tmp_path / "again.json").read_text())
    assert again["settings"] == settings and again["methods"] == data["methods"]

    # another input size: the settings tell the runs apart
    run_main(capsys, "evaluate", "--dataset", "demo", "--descriptor", descriptor, *OTHER_FLAGS, "--runs", "2",
             "--json", str(tmp_path / "other.json"))
    other = settings_of(tmp_path / "other.json")
    assert other[HUB_SETTING] == "--hub-arg width=4 --hub-size 48 48" and other != settings
    assert without_hub(other) == without_hub(settings)


def test_evaluate_without_hub_flags_records_the_settings_it_always_did(tmp_path, capsys):
    out = run_main(capsys, "evaluate", "--dataset", "demo", "--descriptor", "pixels", "--runs", "2",
                   "--json", str(tmp_path / "pixels.json"))
    settings = settings_of(tmp_path / "pixels.json")
    assert settings == evaluate_dataset("demo", PlaceSpec(3, 10), "pixels", "paper", runs=2).settings
    assert HUB_SETTING not in settings and HUB_SETTING not in out


def test_evaluate_of_a_database_queries_folder_records_the_flags(descriptor, positions, tmp_path, capsys):
    common = ["evaluate", "--dataset", str(positions), "--group", "1", "--step", "1"]
    run_main(capsys, *common, "--descriptor", descriptor, *FLAGS, "--json", str(tmp_path / "hub.json"))
    run_main(capsys, *common, "--descriptor", "pixels", "--json", str(tmp_path / "pixels.json"))
    hub, pixels = settings_of(tmp_path / "hub.json"), settings_of(tmp_path / "pixels.json")
    assert after(hub, "descriptor") == HUB_SETTING and after(hub, HUB_SETTING) == "dtype"
    assert hub[HUB_SETTING] == RECORDED
    assert HUB_SETTING not in pixels
    assert list(pixels) == list(without_hub(hub))
    assert {k: v for k, v in pixels.items() if k != "descriptor"} == {
        k: v for k, v in without_hub(hub).items() if k != "descriptor"}


# --------------------------------------------------------------------------- acceptance, failures, sweep


def test_acceptance_records_the_flags(descriptor, tmp_path, capsys):
    run_main(capsys, "acceptance", "--dataset", "demo", "--descriptor", descriptor, *FLAGS,
             "--json", str(tmp_path / "hub.json"))
    run_main(capsys, "acceptance", "--dataset", "demo", "--descriptor", descriptor, *OTHER_FLAGS,
             "--json", str(tmp_path / "other.json"))
    run_main(capsys, "acceptance", "--dataset", "demo", "--descriptor", "pixels", "--json", str(tmp_path / "px.json"))
    hub, other, pixels = (settings_of(tmp_path / f"{n}.json") for n in ("hub", "other", "px"))
    assert after(hub, "descriptor") == HUB_SETTING and after(hub, HUB_SETTING) == "dtype"
    assert (hub[HUB_SETTING], other[HUB_SETTING]) == (RECORDED, "--hub-arg width=4 --hub-size 48 48")
    assert HUB_SETTING not in pixels and after(pixels, "descriptor") == "dtype"
    assert list(pixels) == list(without_hub(hub))


def test_failures_show_the_flags_on_the_index(descriptor, tmp_path, capsys):
    run_main(capsys, "failures", "--dataset", "demo", "--descriptor", descriptor, *FLAGS, "--out",
             str(tmp_path / "hub"), "--limit", "2")
    run_main(capsys, "failures", "--dataset", "demo", "--descriptor", "pixels", "--out", str(tmp_path / "px"),
             "--limit", "2")
    hub = (tmp_path / "hub" / "index.html").read_text()
    pixels = (tmp_path / "px" / "index.html").read_text()
    assert f"<dt>descriptor</dt><dd>{descriptor}</dd><dt>{HUB_SETTING}</dt><dd>{RECORDED}</dd>" in hub
    assert HUB_SETTING not in pixels and "<dt>descriptor</dt><dd>pixels</dd><dt>method</dt>" in pixels


def test_sweep_records_the_flags_in_its_json_and_csv(descriptor, tmp_path, capsys):
    grid = ["--groups", "3", "--steps", "10", "--no-pr", "--runs", "1"]
    out = run_main(capsys, "sweep", "--dataset", "demo", "--descriptor", descriptor, *FLAGS, *grid,
                   "--json", str(tmp_path / "hub.json"), "--csv", str(tmp_path / "hub.csv"))
    assert f"paper protocol, {descriptor} {RECORDED}, method" in out  # the grids' header line
    out = run_main(capsys, "sweep", "--dataset", "demo", "--descriptor", "pixels", *grid,
                   "--json", str(tmp_path / "px.json"), "--csv", str(tmp_path / "px.csv"))
    assert "paper protocol, pixels, method" in out and "--hub" not in out
    hub, pixels = settings_of(tmp_path / "hub.json"), settings_of(tmp_path / "px.json")
    assert after(hub, "descriptor") == HUB_SETTING and hub[HUB_SETTING] == RECORDED
    assert HUB_SETTING not in pixels and list(pixels) == list(without_hub(hub))
    rows = list(csv.DictReader(io.StringIO((tmp_path / "hub.csv").read_text())))
    assert rows and all(r[HUB_SETTING] == RECORDED for r in rows)
    assert HUB_SETTING not in (tmp_path / "px.csv").read_text().splitlines()[0].split(",")


# --------------------------------------------------------------------------- bench


def test_bench_records_the_flags_in_the_hub_descriptors_cells_only(descriptor, tmp_path, capsys):
    run_main(capsys, "bench", "--datasets", "demo", "--descriptors", "pixels", descriptor, *FLAGS,
             "--protocols", "paper", "traversal", "--runs", "1", "--out", str(tmp_path / "bench"))
    data = json.loads((tmp_path / "bench" / "bench.json").read_text())
    cells = {(c["descriptor"], c["protocol"]): c for c in data["cells"]}
    assert set(cells) == {(d, p) for d in ("pixels", descriptor) for p in ("paper", "traversal")}
    for (name, protocol), cell in cells.items():
        assert cell["error"] is None
        settings = cell["evaluation"]["settings"]
        if name == descriptor:
            assert after(settings, "descriptor") == HUB_SETTING and settings[HUB_SETTING] == RECORDED
            assert f"--descriptor {descriptor} {RECORDED} " in cell["evaluate"]
        else:
            assert HUB_SETTING not in settings and "--hub" not in cell["evaluate"]
            assert after(settings, "descriptor") == "dtype"
    steps = {d["descriptor"]: d for d in data["descriptors"]}
    assert steps[descriptor][HUB_SETTING] == RECORDED and HUB_SETTING not in steps["pixels"]

    # a hub cell records what its evaluate command, run alone, records
    cell = cells[(descriptor, "paper")]
    argv = shlex.split(cell["evaluate"])[1:]
    run_main(capsys, *argv, "--json", str(tmp_path / "alone.json"))
    assert settings_of(tmp_path / "alone.json") == cell["evaluation"]["settings"]
