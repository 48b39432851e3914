"""``--descriptors FILE`` through the command line: a file computed elsewhere gives the same table."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vpr_explorer.cli import main
from vpr_explorer.descriptors import write_descriptor_file

pytestmark = pytest.mark.realdata


def _methods(path):
    return json.loads(path.read_text())["methods"]


def test_evaluate_with_a_descriptor_file_equals_extraction(tmp_path, data_root, gardens_point, gp_pixels, capsys):
    gp = str(data_root / "GardensPointWalking")
    order = np.random.default_rng(0).permutation(gardens_point.n_images)  # a file in its own order
    path = tmp_path / "my-netvlad.npz"
    write_descriptor_file(path, gp_pixels[order], [gardens_point.image_paths[i] for i in order], gardens_point.root)
    assert main(["evaluate", "--dataset", gp, "--descriptor", "pixels", "--runs", "3",
                 "--json", str(tmp_path / "a.json")]) == 0
    assert main(["evaluate", "--dataset", gp, "--descriptors", str(path), "--runs", "3",
                 "--json", str(tmp_path / "b.json")]) == 0
    out = capsys.readouterr().out
    assert "descriptor=my-netvlad" in out  # the file's stem names the descriptor
    assert _methods(tmp_path / "b.json") == _methods(tmp_path / "a.json")
    assert json.loads((tmp_path / "b.json").read_text())["settings"]["descriptor"] == "my-netvlad"
    # one or the other
    assert main(["evaluate", "--dataset", gp, "--descriptor", "pixels", "--descriptors", str(path)]) == 2
    assert "give one" in capsys.readouterr().err
    # a file missing images names them
    write_descriptor_file(tmp_path / "short.npz", gp_pixels[:590], gardens_point.image_paths[:590], gardens_point.root)
    assert main(["evaluate", "--dataset", gp, "--descriptors", str(tmp_path / "short.npz"), "--runs", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "night_right/Image190.jpg" in err


def test_record_and_benchmark_layouts_take_a_descriptor_file(tmp_path, data_root, gardens_point, gp_pixels, capsys):
    from vpr_explorer.data.example_layouts import write_gardens_point_layouts
    from vpr_explorer.pipeline import open_dataset

    path = tmp_path / "gp.npy"
    write_descriptor_file(path, gp_pixels, gardens_point.image_paths, gardens_point.root)
    rrd = tmp_path / "run.rrd"
    assert main(["record", "--dataset", str(data_root / "GardensPointWalking"), "--descriptors", str(path),
                 "--database", "day_right", "--queries", "night_right", "--out", str(rrd)]) == 0
    assert rrd.stat().st_size > 0
    layouts = write_gardens_point_layouts(data_root / "GardensPointWalking", tmp_path / "layouts")
    vb = open_dataset(layouts["vpr-bench"])
    rows = {p.resolve(): i for i, p in enumerate(gardens_point.image_paths)}
    d = gp_pixels[[rows[p.resolve()] for p in vb.image_paths]]
    write_descriptor_file(tmp_path / "vb.h5", d, vb.image_paths, vb.root)
    capsys.readouterr()
    assert main(["evaluate", "--dataset", str(layouts["vpr-bench"]), "--descriptors", str(tmp_path / "vb.h5"),
                 "--json", str(tmp_path / "h5.json")]) == 0
    assert main(["evaluate", "--dataset", str(layouts["vpr-bench"]), "--descriptor", "pixels",
                 "--json", str(tmp_path / "px.json")]) == 0
    assert _methods(tmp_path / "h5.json") == _methods(tmp_path / "px.json")
