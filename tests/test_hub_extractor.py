"""torch.hub repositories as extractors (``hub:DIR[:ENTRY]``): end to end, cached, resumed, on Ray, refused.

The repositories are written here: a ``hubconf.py`` with a small convolution, one with a
patch-14 ViT of timm (random weights, seeded), and folders named like the published ones
(MegaLoc, Bag-of-Queries, CosPlace) holding stand-ins, to check the table of their inputs.
Images are real GardensPoint frames; each model's vectors are checked against the model
called by hand (the hubconf executed by hand, the images resized and normalised by hand).
"""

from __future__ import annotations

import re
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from cli_run import assert_one_error_line, refused, run
from test_ray import cluster  # noqa: F401  (the fixture: a local Ray instance)

from vpr_explorer.descriptors import DescriptorCache, extract_descriptors, get_extractor
from vpr_explorer.descriptors import hub
from vpr_explorer.descriptors.cache import hash_file
from vpr_explorer.descriptors.registry import RUNTIME_OPTIONS, available_extractors, cache_name, extractor_options
from vpr_explorer.errors import VPRInputError

ROOT = Path(__file__).resolve().parents[1]
MEAN = np.array([0.485, 0.456, 0.406])
STD = np.array([0.229, 0.224, 0.225])
SIZE = (64, 48)  # width, height fed to the convolution

CONV_HUBCONF = '''
dependencies = ["torch"]

import time

import torch


class TinyConv(torch.nn.Module):
    """A strided 3x3 convolution, then the mean over positions: (B, 3, H, W) -> (B, width)."""

    def __init__(self, width, delay):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, width, 3, stride=2)
        self.delay = delay

    def forward(self, x):
        if self.delay:
            time.sleep(self.delay)
        return self.conv(x).mean(dim=(2, 3))


def tiny_conv(width: int = 8, delay: float = 0.0, seed=0):
    torch.manual_seed(seed)
    return TinyConv(width, delay)
'''

VIT_HUBCONF = '''
dependencies = ["torch", "timm"]

import torch
from timm.models.vision_transformer import VisionTransformer


def tiny_vit(embed_dim: int = 32):
    torch.manual_seed(0)
    return VisionTransformer(img_size=56, patch_size=14, embed_dim=embed_dim, depth=2, num_heads=2, num_classes=0,
                             dynamic_img_size=True)
'''


def write_repo(folder: Path, hubconf: str, **files: str) -> Path:
    folder.mkdir(parents=True)
    (folder / "hubconf.py").write_text(textwrap.dedent(hubconf))
    for name, text in files.items():
        (folder / name).write_text(textwrap.dedent(text))
    return folder


def by_hand(hubconf: Path, entry: str, paths: list[Path], size: tuple[int, int], imagenet: bool = True,
            **kwargs) -> np.ndarray:
    """The entry's model (hubconf executed by hand) on the images resized and normalised by hand, L2-normalised."""
    namespace: dict = {"__name__": "by_hand_hubconf"}
    exec(compile(hubconf.read_text(), str(hubconf), "exec"), namespace)
    model = namespace[entry](**kwargs).eval()
    rows = []
    for path in paths:
        with Image.open(path) as image:
            pixels = np.asarray(image.convert("RGB").resize(size, Image.BILINEAR), dtype=np.float64) / 255.0
        if imagenet:
            pixels = (pixels - MEAN) / STD
        rows.append(pixels.transpose(2, 0, 1))
    with torch.no_grad():
        out = model(torch.tensor(np.stack(rows), dtype=torch.float32)).double().numpy()
    return out / np.linalg.norm(out, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def repos(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hub")
    write_repo(root / "convnet", CONV_HUBCONF)
    write_repo(root / "vit", VIT_HUBCONF)
    return root


@pytest.fixture(scope="module")
def frames(data_root) -> list[Path]:
    """Eight GardensPoint frames: day_left and night_right, 100-103."""
    gp = data_root / "GardensPointWalking"
    return [gp / t / f"Image{i:03d}.jpg" for t in ("day_left", "night_right") for i in range(100, 104)]


def small_dataset(root: Path, data_root: Path, frames: int) -> Path:
    """A traversal-folder dataset of the first ``frames`` GardensPoint frames of day_left and night_right."""
    for traversal in ("day_left", "night_right"):
        (root / traversal).mkdir(parents=True)
        for i in range(frames):
            name = f"Image{100 + i:03d}.jpg"
            shutil.copy(data_root / "GardensPointWalking" / traversal / name, root / traversal / name)
    return root


# ------------------------------------------------------------------ names and arguments


def test_hub_values_are_read_by_the_documented_rules():
    cases = {"None": None, "null": None, "none": None, "true": True, "False": False, "8": 8, "-3": -3, "+2": 2,
             "0.5": 0.5, "1e-3": 1e-3, "-2.": -2.0, ".5": 0.5, "'8'": "8", '"true"': "true", "ResNet50": "ResNet50",
             "": "", "1.2.3": "1.2.3", "nan": "nan", "'": "'"}
    for text, value in cases.items():
        got = hub.parse_hub_value(text)
        assert got == value and type(got) is type(value), (text, got)
    assert hub.hub_arguments(["width=8", "backbone=ResNet50", "pretrained=false"]) == (
        ("backbone", "ResNet50"), ("pretrained", False), ("width", 8))
    assert hub.hub_arguments({"b": 1, "a": None}) == (("a", None), ("b", 1))
    assert hub.hub_arguments(["x= 2 "]) == (("x", 2),)
    for bad, says in ((["width"], "write key=value"), (["1x=2"], "Python identifier"), (["a=1", "a=2"], "twice"),
                      ({"a": [1]}, "must be None, a bool, a number or a string"), ("a=1", "list of key=value")):
        with pytest.raises(VPRInputError, match=says):
            hub.hub_arguments(bad)


def test_a_hub_name_splits_into_folder_and_entry(tmp_path, monkeypatch):
    assert hub.split_hub_name("hub:/a/b:get_model") == (Path("/a/b"), "get_model")
    assert hub.split_hub_name("hub:/a/b") == (Path("/a/b"), None)
    assert hub.split_hub_name("hub:/a/b:") == (Path("/a/b:"), None)  # no identifier after the colon: all folder
    assert hub.split_hub_name("hub:/a/b:1x") == (Path("/a/b:1x"), None)
    monkeypatch.chdir(tmp_path)
    assert hub.split_hub_name("hub:rel:e") == (tmp_path / "rel", "e")
    with pytest.raises(VPRInputError, match="give hub:DIR or hub:DIR:ENTRY"):
        hub.split_hub_name("hub:")


def test_the_registry_accepts_hub_names_with_their_options(repos):
    name = f"hub:{repos / 'convnet'}"
    assert extractor_options(name) == hub.OPTIONS + RUNTIME_OPTIONS
    assert cache_name(name) == "hub.convnet.tiny_conv" == cache_name(name + ":tiny_conv")
    assert cache_name("pixels") == "pixels"
    assert not any(n.startswith("hub") for n in available_extractors())  # one per folder: never listed
    with pytest.raises(VPRInputError, match=r"has no option weights: it accepts hub_args, input_size"):
        get_extractor(name, weights="x.pth")
    with pytest.raises(VPRInputError, match=r"'netvlad' is unknown: choose one of .*, or hub:DIR\[:ENTRY\]"):
        get_extractor("netvlad")


# ------------------------------------------------------------------ end to end


@pytest.mark.realdata
def test_conv_model_matches_the_model_by_hand_and_is_read_back_from_the_cache(repos, frames, tmp_path, monkeypatch):
    repo = repos / "convnet"
    cache = DescriptorCache(tmp_path / "cache")
    extractor = get_extractor(f"hub:{repo}", hub_args=["width=12"], input_size=SIZE, device="cpu")
    assert extractor.dim == 12
    assert re.fullmatch(r"hub\.convnet\.tiny_conv-2\.64x48\.imagenet\.[0-9a-f]{12}", extractor.cache_key)
    got = extract_descriptors(frames, extractor, cache=cache, batch_size=3)
    np.testing.assert_allclose(got, by_hand(repo / "hubconf.py", "tiny_conv", frames, SIZE, width=12), atol=2e-6)

    def no_model(batch):
        raise AssertionError("the model ran: the cache was not read")

    again = get_extractor(f"hub:{repo}:tiny_conv", hub_args={"width": 12}, input_size=list(SIZE), device="cpu")
    assert again.cache_key == extractor.cache_key
    monkeypatch.setattr(again, "forward", no_model)
    assert extract_descriptors(frames, again, cache=cache).tobytes() == got.tobytes()

    unit = get_extractor(f"hub:{repo}", hub_args=["width=12"], input_size=SIZE, normalisation="unit", device="cpu")
    np.testing.assert_allclose(extract_descriptors(frames[:3], unit),
                               by_hand(repo / "hubconf.py", "tiny_conv", frames[:3], SIZE, imagenet=False, width=12),
                               atol=2e-6)


@pytest.mark.realdata
def test_patch_14_vit_matches_the_model_by_hand_and_refuses_other_sides(repos, frames):
    repo = repos / "vit"
    extractor = get_extractor(f"hub:{repo}", input_size=(70, 42), device="cpu")
    assert extractor.dim == 32
    np.testing.assert_allclose(extract_descriptors(frames, extractor, batch_size=4),
                               by_hand(repo / "hubconf.py", "tiny_vit", frames, (70, 42)), atol=2e-5)
    with pytest.raises(VPRInputError) as info:
        get_extractor(f"hub:{repo}", input_size=(60, 40), device="cpu")
    message = str(info.value)
    assert f"tiny_vit() of {repo} is a ViT with patch 14" in message and "--hub-size 56 42" in message, message
    with pytest.raises(VPRInputError, match="short_side=200 leaves the long side free"):
        get_extractor(f"hub:{repo}", short_side=200, device="cpu")


def test_known_models_get_their_authors_input(tmp_path):
    stand_in = '''
        dependencies = ["torch"]
        import pathlib
        import torch
        pathlib.Path(__file__).with_name("imported").touch()  # proves whether the hubconf ran


        class Pair(torch.nn.Module):
            """Returns (descriptor, attentions), as Bag-of-Queries does."""

            def __init__(self, dim):
                super().__init__()
                self.conv = torch.nn.Conv2d(3, dim, 5, stride=4)

            def forward(self, x):
                y = self.conv(x).mean(dim=(2, 3))
                return y, y[:, :2]


        def {entry}({args}):
            torch.manual_seed(0)
            return Pair(4)
    '''
    megaloc = write_repo(tmp_path / "gmberton_MegaLoc_main", stand_in.format(entry="get_trained_model", args=""))
    boq = write_repo(tmp_path / "amaralibey_Bag-of-Queries_main",
                     stand_in.format(entry="get_trained_boq", args="backbone_name='resnet50', output_dim=16384"))
    cosplace = write_repo(tmp_path / "CosPlace", stand_in.format(entry="get_trained_model",
                                                                 args="backbone='ResNet50', fc_output_dim=2048"))

    # A side that is not a multiple of DINOv2's 14 is refused from the table, before the hubconf runs.
    with pytest.raises(VPRInputError) as info:
        get_extractor(f"hub:{megaloc}", input_size=(320, 320), device="cpu")
    assert f"get_trained_model() of {megaloc} is a ViT with patch 14" in str(info.value)
    assert "--hub-size 322 322" in str(info.value)
    with pytest.raises(VPRInputError, match=r"get_trained_boq\(backbone_name='dinov2'\) .* --hub-size 294 294"):
        get_extractor(f"hub:{boq}", hub_args=["backbone_name=dinov2"], input_size=300, device="cpu")
    assert not (megaloc / "imported").exists() and not (boq / "imported").exists()

    keys = {
        "megaloc": get_extractor(f"hub:{megaloc}", device="cpu").cache_key,
        "boq-resnet": get_extractor(f"hub:{boq}", device="cpu").cache_key,
        "boq-dinov2": get_extractor(f"hub:{boq}", hub_args=["backbone_name=dinov2"], device="cpu").cache_key,
        "cosplace": get_extractor(f"hub:{cosplace}", hub_args=["fc_output_dim=512"], device="cpu").cache_key,
        "megaloc-unit": get_extractor(f"hub:{megaloc}", normalisation="unit", device="cpu").cache_key,
    }
    assert ".322x322.imagenet." in keys["megaloc"] and ".384x384.imagenet." in keys["boq-resnet"]
    assert ".322x322.imagenet." in keys["boq-dinov2"] and ".s480.imagenet." in keys["cosplace"]
    assert ".322x322.unit." in keys["megaloc-unit"]
    assert keys["megaloc"].startswith("hub.gmberton_MegaLoc_main.get_trained_model-")
    # The tuple's first element is the descriptor.
    extractor = get_extractor(f"hub:{boq}", device="cpu")
    assert extractor.dim == 4 and extractor.forward(np.ones((2, 3, 384, 384), np.float32)).shape == (2, 4)


# ------------------------------------------------------------------ the cache key


def test_the_key_follows_the_hubconf_the_arguments_the_input_and_the_commit(repos, tmp_path):
    repo = shutil.copytree(repos / "convnet", tmp_path / "convnet")
    name = f"hub:{repo}"

    def key(**options) -> str:
        options = {"hub_args": ["width=8"], "input_size": SIZE, "device": "cpu", **options}
        return get_extractor(name, **options).cache_key

    first = key()
    assert key() == first
    assert key(hub_args=["width=8", "seed=0"]) != first  # an argument given, even at its default
    assert key(hub_args=["width=9"]) != first
    assert key(input_size=(64, 64)) != first and key(normalisation="signed") != first
    (repo / "hubconf.py").write_text((repo / "hubconf.py").read_text() + "\n# edited\n")
    edited = key()
    assert edited != first
    (repo / "helpers.py").write_text("X = 1\n")  # any .py of the repository
    with_helper = key()
    assert with_helper != edited
    (repo / "__pycache__").mkdir()
    (repo / "__pycache__" / "x.py").write_text("junk")
    (repo / "README.md").write_text("not code")
    assert key() == with_helper

    # Argument types are part of the key: 1 and 1.0 and "1" differ.
    spec = hub.hub_model(name, hub_args={"seed": 1}, input_size=SIZE)
    digests = {hub.model_digest(hub.hub_model(name, hub_args={"seed": v}, input_size=SIZE), "id") for v in
               (1, 1.0, "1", True)}
    assert len(digests) == 4 and hub.model_digest(spec, "id") in digests

    # A git checkout: the commit HEAD names joins the key.
    git = repo / ".git"
    (git / "refs" / "heads").mkdir(parents=True)
    (git / "HEAD").write_text("ref: refs/heads/main\n")
    (git / "refs" / "heads" / "main").write_text("a" * 40 + "\n")
    assert hub.git_commit(repo) == "a" * 40
    on_a = key()
    assert on_a != with_helper
    (git / "refs" / "heads" / "main").unlink()
    (git / "packed-refs").write_text(f"# pack-refs with: peeled\n{'b' * 40} refs/heads/main\n")
    assert hub.git_commit(repo) == "b" * 40
    assert key() != on_a
    (git / "HEAD").write_text("c" * 40 + "\n")  # detached
    assert hub.git_commit(repo) == "c" * 40
    (git / "HEAD").write_text("ref: refs/heads/../../../etc\n")
    assert hub.git_commit(repo) is None
    shutil.rmtree(git)
    (git.parent / "real.git").mkdir()
    (git.parent / "real.git" / "HEAD").write_text("d" * 40)
    git.write_text("gitdir: real.git\n")  # a worktree or submodule
    assert hub.git_commit(repo) == "d" * 40
    assert hub.repo_identity(repo).startswith(f"git:{'d' * 40}|py:")


# ------------------------------------------------------------------ resume


CHILD = """
    import signal, sys
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from vpr_explorer.data.traversals import load_dataset
    from vpr_explorer.descriptors import DescriptorCache, ExtractionInterrupted, extract_descriptors, get_extractor

    dataset = load_dataset(sys.argv[1])
    extractor = get_extractor(sys.argv[3], hub_args=["delay=0.1"], input_size=(64, 48), device="cpu")

    def progress(done, total):
        print(done, total, flush=True)

    try:
        extract_descriptors(list(dataset.image_paths), extractor, cache=DescriptorCache(sys.argv[2]), batch_size=2,
                            workers=1, progress=progress)
    except ExtractionInterrupted as exc:
        print(f"interrupted: {exc}", file=sys.stderr)
        sys.exit(130)
"""


@pytest.mark.realdata
def test_ctrl_c_keeps_the_finished_batches_and_the_rerun_computes_only_the_rest(repos, data_root, tmp_path,
                                                                                 monkeypatch):
    dataset = small_dataset(tmp_path / "gp", data_root, 12)
    name = f"hub:{repos / 'convnet'}"
    root = tmp_path / "cache"
    script = tmp_path / "child.py"
    script.write_text(textwrap.dedent(CHILD))
    proc = subprocess.Popen([sys.executable, str(script), str(dataset), str(root), name], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT)
    for line in proc.stdout:
        if int(line.split()[0]) >= 6:
            proc.send_signal(signal.SIGINT)
            break
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    n_cached = int(re.search(r"interrupted: (\d+) of 24 descriptors cached", err)[1])
    assert 6 <= n_cached < 24

    from vpr_explorer.data.traversals import load_dataset

    paths = list(load_dataset(dataset).image_paths)
    extractor = get_extractor(name, hub_args=["delay=0.1"], input_size=SIZE, device="cpu")
    forward, seen = extractor.forward, []

    def counting(batch):
        seen.append(len(batch))
        return forward(batch)

    monkeypatch.setattr(extractor, "forward", counting)
    calls = []
    resumed = extract_descriptors(paths, extractor, cache=DescriptorCache(root), batch_size=4,
                                  progress=lambda d, t: calls.append(d))
    assert calls[0] == n_cached and sum(seen) == 24 - n_cached
    clean = extract_descriptors(paths, extractor)
    np.testing.assert_allclose(resumed, clean, atol=1e-6)


# ------------------------------------------------------------------ the command line


@pytest.mark.realdata
def test_extract_command_fills_the_cache_then_finds_it(repos, data_root, tmp_path):
    dataset = small_dataset(tmp_path / "gp", data_root, 4)
    repo = repos / "convnet"
    args = ("extract", "--dataset", str(dataset), "--descriptor", f"hub:{repo}:tiny_conv", "--hub-arg", "width=6",
            "--hub-size", "64", "48", "--hub-normalisation", "unit", "--cache-dir", str(tmp_path / "cache"))
    first = run(*args, timeout=300)
    assert first.returncode == 0, first.stderr[-2000:]
    assert re.match(r"8 images: 0 already cached, 8 computed locally", first.stdout.strip().splitlines()[-1])
    second = run(*args, timeout=300)
    assert second.returncode == 0, second.stderr[-2000:]
    assert re.match(r"8 images: 8 already cached, 0 computed locally", second.stdout.strip().splitlines()[-1])

    from vpr_explorer.data.traversals import load_dataset

    paths = list(load_dataset(dataset).image_paths)
    extractor = get_extractor(f"hub:{repo}", hub_args={"width": 6}, input_size=SIZE, normalisation="unit")
    index, vectors = DescriptorCache(tmp_path / "cache").lookup(extractor.cache_key, [hash_file(p) for p in paths], 6)
    assert len(index) == 8
    np.testing.assert_allclose(vectors, by_hand(repo / "hubconf.py", "tiny_conv",
                                                [paths[i] for i in index], SIZE, imagenet=False, width=6), atol=2e-6)


@pytest.mark.realdata
def test_the_command_line_refuses_bad_hub_input_in_one_line(repos, data_root, tmp_path, capsys):
    dataset = small_dataset(tmp_path / "gp", data_root, 2)
    base = ("extract", "--dataset", str(dataset), "--cache-dir", str(tmp_path / "cache"))
    assert_one_error_line(refused(capsys, *base, "--descriptor", "pixels", "--hub-size", "64", "48"),
                          "--hub-size apply to --descriptor hub:DIR[:ENTRY] only", "--descriptor pixels")
    assert_one_error_line(refused(capsys, *base, "--descriptor", f"hub:{tmp_path}"),
                          f"hub repository {tmp_path}", "has no hubconf.py")
    assert_one_error_line(refused(capsys, *base, "--descriptor", f"hub:{repos / 'convnet'}"),
                          "tiny_conv()", "is not one of the known models", "--hub-size W H")
    assert_one_error_line(refused(capsys, *base, "--descriptor", f"hub:{repos / 'convnet'}", "--hub-size", "64", "48",
                                  "--hub-arg", "depth=3"),
                          "has no argument depth: it takes width=8, delay=0.0, seed=0")


# ------------------------------------------------------------------ refused repositories, entries, models


BROKEN = {
    "no_dependency": ('dependencies = ["torch", "no_such_package_for_vpr_hub"]\ndef entry():\n    pass\n',
                      "Missing dependencies: no_such_package_for_vpr_hub"),
    "import_fails": ("import no_such_module_for_vpr_hub\ndef entry():\n    pass\n",
                     "importing its hubconf.py failed (ModuleNotFoundError: No module named "
                     "'no_such_module_for_vpr_hub')"),
    "raises_on_import": ('raise ValueError("set HUB_WEIGHTS first")\ndef entry():\n    pass\n',
                         "importing its hubconf.py failed (ValueError: set HUB_WEIGHTS first)"),
    "syntax": ("def entry(:\n    pass\n", "line 1 is not valid Python"),
    "two_entries": ("def a():\n    pass\ndef b():\n    pass\n", "defines 2 public entries (a, b); name one"),
    "no_entry": ("def _private():\n    pass\n", "defines 0 public entries (none); name one"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_a_broken_repository_is_refused_naming_it(tmp_path, case):
    text, says = BROKEN[case]
    repo = write_repo(tmp_path / case, text)
    with pytest.raises(VPRInputError) as info:
        get_extractor(f"hub:{repo}", input_size=32, device="cpu")
    assert says in str(info.value) and str(repo) in str(info.value), str(info.value)


def test_a_missing_folder_or_hubconf_is_unavailable_and_named(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "file").write_text("x")
    for folder, says in (("empty", "has no hubconf.py"), ("file", "is not a folder"), ("absent", "is not a folder")):
        with pytest.raises(VPRInputError, match=f"is unavailable here: hub repository {re.escape(str(tmp_path))}/"
                                                f"{folder} .*{says}"):
            get_extractor(f"hub:{tmp_path / folder}", input_size=32)


ENTRIES = '''
dependencies = ["torch"]
import torch


class Net(torch.nn.Module):
    def __init__(self, mode="ok"):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 4, 3)
        self.mode = mode

    def forward(self, x):
        y = self.conv(x)
        if self.mode == "fails":
            raise RuntimeError("mat1 and mat2 shapes cannot be multiplied")
        if self.mode == "map":
            return y  # (B, 4, H-2, W-2): no global descriptor
        if self.mode == "dict":
            return {"global": y.mean(dim=(2, 3))}
        return y.mean(dim=(2, 3))


def good(mode="ok"):
    return Net(mode)


def needs_width(width):
    return Net()


def broken():
    raise ValueError("weights not found")


def flexible(**kwargs):
    return Net(**kwargs)


def not_a_model():
    return "a string"


def online():
    import urllib.request
    urllib.request.urlopen("http://127.0.0.1:9/weights.pth", timeout=5)
'''


def test_entries_and_models_that_fail_are_refused_naming_repository_entry_and_fix(tmp_path):
    repo = write_repo(tmp_path / "entries", ENTRIES)
    cases = [
        ("nope", {}, "hubconf.py has no entry 'nope' (its public functions: good, needs_width, broken, flexible, "
                     "not_a_model, online); name one as hub:"),
        ("good", {"depth": 3}, f"hub entry good(depth=3) of {repo} has no argument depth: it takes mode='ok'"),
        ("needs_width", {}, f"hub entry needs_width() of {repo} needs width: it takes width; add --hub-arg width=..."),
        ("broken", {}, f"hub entry broken() of {repo} failed (ValueError: weights not found); check its --hub-arg"),
        ("flexible", {"depth": 3}, f"hub entry flexible(depth=3) of {repo} failed (TypeError: "),
        ("not_a_model", {}, f"hub entry not_a_model() of {repo} returned str, not a model"),
        ("online", {}, "failed (URLError: <urlopen error [Errno 111] Connection refused>); it downloads something "
                       "(weights, another hub repository): fill the torch hub cache on a networked machine"),
        ("good", {"mode": "fails"}, f"hub model good(mode='fails') of {repo} fails on a (1, 3, 24, 32) batch "
                                    "(RuntimeError: mat1 and mat2 shapes cannot be multiplied); check the input size"),
        ("good", {"mode": "map"}, f"hub model good(mode='map') of {repo} maps a (1, 3, 24, 32) batch to shape "
                                  "(1, 4, 22, 30); it must return (B, D)"),
        ("good", {"mode": "dict"}, "the model returned dict, not a tensor"),
    ]
    for entry, args, says in cases:
        with pytest.raises(VPRInputError) as info:
            get_extractor(f"hub:{repo}:{entry}", hub_args=args, input_size=(32, 24), device="cpu")
        assert says in str(info.value), (entry, str(info.value))
    assert get_extractor(f"hub:{repo}:good", input_size=(32, 24), device="cpu").dim == 4


# ------------------------------------------------------------------ Ray


@pytest.mark.realdata
def test_ray_fills_the_same_cache_and_a_second_job_finds_it(repos, frames, tmp_path, cluster):
    from vpr_explorer.descriptors.distributed import extract_on_ray

    name = f"hub:{repos / 'convnet'}"
    options = {"hub_args": ("width=5",), "input_size": SIZE, "device": "cpu"}
    # address None: the jobs use this process's connection to test_ray's local instance
    first = extract_on_ray(frames, name, options=options, cache_root=tmp_path / "cache", batch_size=2, shard_images=4)
    second = extract_on_ray(frames, name, options=options, cache_root=tmp_path / "cache")
    assert (first.computed, first.cached) == (8, 0) and (second.computed, second.cached) == (0, 8)
    extractor = get_extractor(name, **options)
    assert first.cache_key == extractor.cache_key
    index, vectors = DescriptorCache(tmp_path / "cache").lookup(extractor.cache_key, [hash_file(p) for p in frames], 5)
    assert sorted(index) == list(range(8))
    np.testing.assert_allclose(vectors[np.argsort(index)], extract_descriptors(frames, extractor), atol=1e-6)
