"""The paper's descriptors (AlexNet conv3, CosPlace, EigenPlaces) and users' own models.

No weights can be downloaded here, so each test writes random-initialised checkpoints in
the official formats (torchvision's AlexNet state dict; the CosPlace / EigenPlaces
``GeoLocalizationNet`` state dict, built below by an independent copy of the published
network) and loads them strictly through the real loading code.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from images import write_random_png
import torch
import torch.nn.functional as F
import torchvision
from PIL import Image

from vpr_explorer.descriptors import (
    DescriptorCache,
    available_extractors,
    extract_descriptors,
    extractor_names,
    get_extractor,
    register_extractor,
    unregister_extractor,
)
from vpr_explorer.descriptors import checkpoints
from vpr_explorer.descriptors.alexnet import FLAT_DIM, PROJECTION_DIM, random_projection
from vpr_explorer.descriptors.custom import MODELS_ENV
from vpr_explorer.descriptors.preprocess import Normalisation, short_side_size, to_chw
from vpr_explorer.errors import VPRInputError

WEIGHT_ENVS = ("VPR_EXPLORER_ALEXNET_WEIGHTS", "VPR_EXPLORER_COSPLACE_WEIGHTS", "VPR_EXPLORER_EIGENPLACES_WEIGHTS")
SHORT = 64  # CosPlace input side in these tests: ResNet-50 at 480 px is seconds per image on 2 cores


@pytest.fixture(autouse=True)
def no_weights_anywhere(monkeypatch, tmp_path):
    """Each test starts with an empty torch hub folder and no weights variables."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    for name in (*WEIGHT_ENVS, MODELS_ENV):
        monkeypatch.delenv(name, raising=False)


def write_rgb(path: Path, seed: int, size: tuple[int, int] = (120, 80)) -> Path:
    return write_random_png(path, seed, size)


@pytest.fixture
def images(tmp_path: Path) -> list[Path]:
    return [write_rgb(tmp_path / f"im{i}.png", seed=i) for i in range(4)]


# ------------------------------------------------------------------ the official formats


class OfficialGeM(torch.nn.Module):
    """gmberton/CosPlace cosplace_model/layers.py, as published."""

    def __init__(self, p=3, eps=1e-6):
        super().__init__()
        self.p = torch.nn.Parameter(torch.ones(1) * p)
        self.eps = eps

    def forward(self, x):
        return F.avg_pool2d(x.clamp(min=self.eps).pow(self.p), (x.size(-2), x.size(-1))).pow(1.0 / self.p)


class OfficialL2Norm(torch.nn.Module):
    def forward(self, x):
        return F.normalize(x, p=2.0, dim=1)


class OfficialFlatten(torch.nn.Module):
    def forward(self, x):
        assert x.shape[2] == x.shape[3] == 1
        return x[:, :, 0, 0]


class OfficialGeoLocalizationNet(torch.nn.Module):
    """cosplace_network.GeoLocalizationNet / eigenplaces_network.GeoLocalizationNet_ (ResNets)."""

    def __init__(self, backbone: str, fc_output_dim: int):
        super().__init__()
        resnet = getattr(torchvision.models, backbone.lower())(weights=None)
        self.backbone = torch.nn.Sequential(*list(resnet.children())[:-2])
        features_dim = {"ResNet18": 512, "ResNet50": 2048}[backbone]
        self.aggregation = torch.nn.Sequential(
            OfficialL2Norm(), OfficialGeM(), OfficialFlatten(), torch.nn.Linear(features_dim, fc_output_dim), OfficialL2Norm()
        )

    def forward(self, x):
        return self.aggregation(self.backbone(x))


def official_place_net(backbone: str, dim: int, seed: int) -> OfficialGeoLocalizationNet:
    torch.manual_seed(seed)
    net = OfficialGeoLocalizationNet(backbone, dim).eval()
    with torch.no_grad():
        net.aggregation[1].p.fill_(3.0 + seed / 10)  # a trained p is not 3: make sure it is read
        # Random BN statistics, so that loading them (not leaving defaults) matters.
        for module in net.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.1, 0.1)
                module.running_var.uniform_(0.5, 1.5)
    return net


@pytest.fixture(scope="module")
def alexnet_file(tmp_path_factory) -> Path:
    """torchvision AlexNet, random weights, saved as its state dict (the official file's format)."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("alexnet") / "alexnet-random.pth"
    torch.save(torchvision.models.alexnet(weights=None).state_dict(), path)
    return path


@pytest.fixture(scope="module")
def cosplace_r50(tmp_path_factory) -> tuple[Path, OfficialGeoLocalizationNet]:
    net = official_place_net("ResNet50", 2048, seed=1)
    path = tmp_path_factory.mktemp("cosplace") / "ResNet50_2048_cosplace.pth"
    torch.save(net.state_dict(), path)
    return path, net


@pytest.fixture(scope="module")
def r18_256(tmp_path_factory) -> tuple[Path, OfficialGeoLocalizationNet]:
    net = official_place_net("ResNet18", 256, seed=2)
    path = tmp_path_factory.mktemp("r18") / "r18_256.pth"
    torch.save(net.state_dict(), path)
    return path, net


# ------------------------------------------------------------------ availability


def test_paper_extractors_are_listed_unavailable_with_where_to_get_the_weights(tmp_path):
    assert {"alexnet-conv3", "cosplace", "eigenplaces"} <= set(extractor_names())
    status = available_extractors()
    hub = tmp_path / "torch_home" / "hub" / "checkpoints"
    expected = {
        "alexnet-conv3": ("alexnet-owt-7be5be79.pth", "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
                          "VPR_EXPLORER_ALEXNET_WEIGHTS"),
        "cosplace": ("ResNet50_2048_cosplace.pth",
                     "https://github.com/gmberton/CosPlace/releases/download/v1.0/ResNet50_2048_cosplace.pth",
                     "VPR_EXPLORER_COSPLACE_WEIGHTS"),
        "eigenplaces": ("ResNet50_2048_eigenplaces.pth",
                        "https://github.com/gmberton/EigenPlaces/releases/download/v1.0/ResNet50_2048_eigenplaces.pth",
                        "VPR_EXPLORER_EIGENPLACES_WEIGHTS"),
    }
    for name, (file_name, url, env) in expected.items():
        reason = status[name]
        assert reason is not None
        for part in (file_name, url, env, str(hub / file_name), "weights=PATH", "download=True"):
            assert part in reason, f"{name}: {part!r} missing from {reason!r}"
        with pytest.raises(VPRInputError, match=f"descriptor '{name}' is unavailable here: no weights file: expected {file_name}"):
            get_extractor(name)


def cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vpr_explorer.cli", *args], capture_output=True, text=True,
                          timeout=300, env={**os.environ, **(env or {})})


def one_error_line(r: subprocess.CompletedProcess) -> str:
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    (line,) = [line for line in r.stderr.splitlines() if line.strip()]
    assert line.startswith("error: ")
    return line


def test_missing_alexnet_weights_tell_a_command_line_user_what_to_do(tmp_path):
    route = tmp_path / "route"
    for traversal in ("day", "night"):
        (route / traversal).mkdir(parents=True)
        for f in range(8):
            write_rgb(route / traversal / f"frame_{f}.png", seed=f)
    args = ["evaluate", "--dataset", str(route), "--descriptor", "alexnet-conv3", "--group", "2", "--step", "4",
            "--cache-dir", str(tmp_path / "cache")]
    hub_file = tmp_path / "torch_home" / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth"
    env = "VPR_EXPLORER_ALEXNET_WEIGHTS"

    line = one_error_line(cli(*args))
    assert line.startswith("error: descriptor 'alexnet-conv3' is unavailable here: no weights file: expected "
                           "alexnet-owt-7be5be79.pth")
    # What works without writing Python: a file at a path, or an environment variable.
    assert f"download https://download.pytorch.org/models/alexnet-owt-7be5be79.pth and put it at {hub_file}" in line
    assert f"or set the environment variable {env} to the file (or to a folder holding it)" in line
    # The API's options are named as such, never as something to pass on a command line.
    assert "pass weights=PATH" not in line and "(from Python, the weights=PATH and download=True options" in line

    # Following either instruction is what the command line reads: the (here bogus) file is found.
    folder = tmp_path / "weights"
    folder.mkdir()
    (folder / hub_file.name).write_bytes(b"not a checkpoint")
    line = one_error_line(cli(*args, env={env: str(folder)}))
    assert line.startswith(f"error: {folder / hub_file.name}: cannot read it as a PyTorch checkpoint")
    hub_file.parent.mkdir(parents=True)
    hub_file.write_bytes(b"not a checkpoint either")
    line = one_error_line(cli(*args))
    assert line.startswith(f"error: {hub_file}: cannot read it as a PyTorch checkpoint")


def test_weights_are_looked_for_in_option_then_variable_then_hub_cache(tmp_path, monkeypatch):
    spec = checkpoints.place_weights("cosplace", "ResNet18", 256)
    hub_file = checkpoints.hub_checkpoint(spec)
    hub_file.parent.mkdir(parents=True)
    hub_file.write_bytes(b"hub")
    assert checkpoints.find_weights(spec) == hub_file
    folder = tmp_path / "weights"
    folder.mkdir()
    (folder / "ResNet18_256_cosplace.pth").write_bytes(b"env")
    monkeypatch.setenv("VPR_EXPLORER_COSPLACE_WEIGHTS", str(folder))  # a folder holding the official name
    assert checkpoints.find_weights(spec) == folder / "ResNet18_256_cosplace.pth"
    mine = tmp_path / "mine.pth"
    mine.write_bytes(b"option")
    assert checkpoints.find_weights(spec, mine) == mine
    # Given but missing: an error, never a silent fall-back to another file.
    assert "weights='" in checkpoints.find_weights(spec, tmp_path / "typo.pth")
    monkeypatch.setenv("VPR_EXPLORER_COSPLACE_WEIGHTS", str(tmp_path / "nowhere.pth"))
    reason = checkpoints.find_weights(spec)
    assert reason.startswith(f"VPR_EXPLORER_COSPLACE_WEIGHTS={tmp_path / 'nowhere.pth'}: no such file")
    with pytest.raises(VPRInputError, match=r"weights='.*typo\.pth': no such file; expected ResNet18_256_cosplace\.pth"):
        get_extractor("cosplace", backbone="ResNet18", fc_output_dim=256, weights=tmp_path / "typo.pth")


def test_torch_hub_dir_follows_torch(monkeypatch, tmp_path):
    import torch.hub

    for env in ({"TORCH_HOME": str(tmp_path / "th")}, {"XDG_CACHE_HOME": str(tmp_path / "xdg")}):
        monkeypatch.delenv("TORCH_HOME", raising=False)
        monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
        for key, value in env.items():
            monkeypatch.setenv(key, value)
        assert checkpoints.torch_hub_dir() == Path(torch.hub.get_dir())


def test_unpublished_backbone_or_dimension_lists_the_published_ones():
    with pytest.raises(VPRInputError, match="backbone='ResNet34': CosPlace publishes no such model; choose one of VGG16, ResNet18"):
        get_extractor("cosplace", backbone="ResNet34")
    with pytest.raises(VPRInputError, match="fc_output_dim=4096: CosPlace ResNet50 is published with 32, 64, .*, 2048"):
        get_extractor("cosplace", fc_output_dim=4096)
    with pytest.raises(VPRInputError, match="EigenPlaces ResNet18 is published with 256, 512 dimensions"):
        get_extractor("eigenplaces", backbone="ResNet18", fc_output_dim=32)
    with pytest.raises(VPRInputError, match="has no option size: it accepts backbone, fc_output_dim, short_side"):
        get_extractor("eigenplaces", size=3)


def test_download_goes_through_torch_hub_into_its_folder(tmp_path):
    published = tmp_path / "server" / "model.pth"
    published.parent.mkdir()
    published.write_bytes(b"weights bytes")
    prefix = hashlib.sha256(b"weights bytes").hexdigest()[:8]
    spec = checkpoints.WeightsSpec("test weights", "model.pth", published.as_uri(), "VPR_TEST_WEIGHTS", prefix)
    assert checkpoints.unavailable_reason(spec) is not None
    assert checkpoints.unavailable_reason(spec, download=True) is None
    with pytest.raises(VPRInputError, match="no weights file: expected model.pth"):
        checkpoints.locate_weights(spec)  # no download unless asked
    got = checkpoints.locate_weights(spec, download=True)
    assert got == checkpoints.hub_checkpoint(spec) and got.read_bytes() == b"weights bytes"
    bad = checkpoints.WeightsSpec("test weights", "other.pth", published.as_uri(), "VPR_TEST_WEIGHTS", "00000000")
    with pytest.raises(VPRInputError, match=r"could not download file://.*model\.pth .*put it at"):
        checkpoints.locate_weights(bad, download=True)
    assert not checkpoints.hub_checkpoint(bad).exists()


# ------------------------------------------------------------------ preprocessing


def test_short_side_rule_is_torchvisions():
    assert short_side_size(960, 540, 480) == (853, 480)  # GardensPoint frames
    assert short_side_size(540, 960, 480) == (480, 853)
    assert short_side_size(640, 640, 480) == (480, 480)
    from torchvision.transforms import Resize

    for w, h in ((960, 540), (333, 500), (1241, 376)):
        resized = Resize(480)(Image.new("RGB", (w, h)))
        assert short_side_size(w, h, 480) == resized.size


def test_default_decoding_threads_follow_the_cores():
    from vpr_explorer.settings import MAX_DEFAULT_WORKERS, default_workers

    assert default_workers() == min(len(os.sched_getaffinity(0)), MAX_DEFAULT_WORKERS)


def test_imagenet_normalisation_by_hand():
    rgb = np.array([[[0, 255, 124]]], dtype=np.uint8)  # (H=1, W=1, 3)
    got = to_chw(rgb, Normalisation.IMAGENET)
    want = [(0 - 0.485) / 0.229, (1 - 0.456) / 0.224, (124 / 255 - 0.406) / 0.225]
    assert got.shape == (3, 1, 1) and got.dtype == np.float32
    np.testing.assert_allclose(got[:, 0, 0], want, rtol=1e-5)
    np.testing.assert_allclose(to_chw(rgb, Normalisation.UNIT)[:, 0, 0], [0, 1, 124 / 255], atol=1e-7)
    np.testing.assert_allclose(to_chw(rgb, Normalisation.SIGNED)[:, 0, 0], [-1, 1, 124 / 127.5 - 1], atol=1e-6)


# ------------------------------------------------------------------ AlexNet conv3


def test_projection_is_vpr_tutorials_seeded_matrix():
    projection = random_projection()
    assert projection.shape == (FLAT_DIM, PROJECTION_DIM) == (64896, 4096)
    # default_rng fills the matrix row by row, so its first rows are the stream's first draws.
    first = np.random.default_rng(seed=0).standard_normal(2 * 4096, dtype=np.float32).reshape(2, 4096)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    np.testing.assert_array_equal(projection[:2].numpy(), first)
    np.testing.assert_allclose(np.linalg.norm(projection[-3:].numpy(), axis=1), 1.0, rtol=1e-5)
    assert random_projection() is projection  # generated once per process


def test_alexnet_conv3_matches_a_reference_and_is_stable(alexnet_file, images):
    extractor = get_extractor("alexnet-conv3", weights=alexnet_file, device="cpu")
    digest = hashlib.sha256(alexnet_file.read_bytes()).hexdigest()
    assert extractor.dim == 4096 and extractor.cache_key == f"alexnet-conv3-2.p0.{digest[:12]}"
    loaded = extractor.load(images[0])
    assert loaded.shape == (3, 224, 224) and loaded.dtype == np.float32
    batch = np.stack([extractor.load(p) for p in images[:3]])

    reference = torchvision.models.alexnet(weights=None).eval()
    reference.load_state_dict(torch.load(alexnet_file, weights_only=True))
    with torch.no_grad():
        conv3 = reference.features[:7](torch.from_numpy(batch))
    assert conv3.shape == (3, 384, 13, 13)
    want = conv3.reshape(3, -1).numpy() @ random_projection().numpy()
    got = extractor.forward(batch)
    assert got.shape == (3, 4096)
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-3 * np.abs(want).max())
    np.testing.assert_array_equal(extractor.forward(batch), got)  # same input, same descriptor

    d = extract_descriptors(images, extractor, batch_size=3)
    assert d.shape == (4, 4096)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(extract_descriptors(images, extractor, batch_size=3), d)
    # Another batching changes the BLAS blocking, so only rounding may differ.
    np.testing.assert_allclose(extract_descriptors(images, extractor, batch_size=2, workers=1), d, atol=1e-6)
    assert get_extractor("alexnet-conv3", weights=alexnet_file, device="cpu") is extractor  # loaded once


def test_alexnet_weights_from_the_variable(alexnet_file, monkeypatch):
    monkeypatch.setenv("VPR_EXPLORER_ALEXNET_WEIGHTS", str(alexnet_file))
    assert available_extractors()["alexnet-conv3"] is None
    assert get_extractor("alexnet-conv3", device="cpu").cache_key.startswith("alexnet-conv3-2.p0.")


def test_alexnet_checkpoint_with_missing_or_renamed_keys_is_refused(tmp_path):
    torch.manual_seed(3)
    features = {k: v for k, v in torchvision.models.alexnet(weights=None).state_dict().items() if k.startswith("features")}
    no_classifier = tmp_path / "features_only.pth"
    torch.save(features, no_classifier)
    with pytest.raises(VPRInputError, match=rf"{no_classifier}: is not a torchvision AlexNet checkpoint \(missing keys: "
                                            r"classifier\.1\.weight, classifier\.1\.bias, classifier\.4\.weight and 3 more\)"):
        get_extractor("alexnet-conv3", weights=no_classifier)

    renamed = dict(features)
    renamed["features.0.kernel"] = renamed.pop("features.0.weight")
    renamed_file = tmp_path / "renamed.pth"
    torch.save(renamed, renamed_file)
    with pytest.raises(VPRInputError, match=r"renamed\.pth: .*missing keys: features\.0\.weight, .*unexpected keys: features\.0\.kernel"):
        get_extractor("alexnet-conv3", weights=renamed_file)

    text = tmp_path / "notes.pth"
    text.write_text("not a checkpoint")
    with pytest.raises(VPRInputError, match=r"notes\.pth: cannot read it as a PyTorch checkpoint .*alexnet-owt-7be5be79\.pth"):
        get_extractor("alexnet-conv3", weights=text)


# ------------------------------------------------------------------ CosPlace / EigenPlaces


def test_cosplace_resnet50_loads_strictly_and_matches_the_published_network(cosplace_r50, images, tmp_path):
    path, official = cosplace_r50
    keys = list(official.state_dict())
    for key in ("backbone.0.weight", "backbone.1.running_var", "backbone.4.0.conv1.weight",
                "backbone.7.2.bn3.num_batches_tracked", "aggregation.1.p", "aggregation.3.weight", "aggregation.3.bias"):
        assert key in keys
    extractor = get_extractor("cosplace", weights=path, short_side=SHORT, device="cpu")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert extractor.dim == 2048 and extractor.cache_key == f"cosplace-2.ResNet50-2048.s{SHORT}.{digest[:12]}"

    batch = np.stack([extractor.load(p) for p in images[:2]])
    assert batch.shape == (2, 3, SHORT, 96)  # 120 x 80 -> 96 x 64: aspect kept
    with torch.no_grad():
        want = official(torch.from_numpy(batch)).numpy()
    got = extractor.forward(batch)
    assert got.shape == (2, 2048)
    np.testing.assert_allclose(got, want, atol=2e-5)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)  # the network's own L2Norm
    np.testing.assert_array_equal(extractor.forward(batch), got)

    # Two aspect ratios in one run: batched by shape, rows stay in order.
    tall = write_rgb(tmp_path / "tall.png", seed=7, size=(60, 100))
    paths = [images[0], tall, images[1]]
    cache = DescriptorCache(tmp_path / "cache")
    d = extract_descriptors(paths, extractor, cache=cache, batch_size=8)
    assert d.shape == (3, 2048)
    np.testing.assert_allclose(d[[0, 2]], got / np.linalg.norm(got, axis=1, keepdims=True), atol=1e-6)
    alone = extract_descriptors([tall], extractor)
    np.testing.assert_allclose(d[1], alone[0], atol=1e-6)
    np.testing.assert_array_equal(extract_descriptors(paths, extractor, cache=cache), d)


def test_eigenplaces_from_torch_hub_cache_and_cosplace_from_a_variable(r18_256, images, tmp_path, monkeypatch):
    path, official = r18_256
    hub_file = tmp_path / "torch_home" / "hub" / "checkpoints" / "ResNet18_256_eigenplaces.pth"
    hub_file.parent.mkdir(parents=True)
    hub_file.write_bytes(path.read_bytes())
    eigen = get_extractor("eigenplaces", backbone="ResNet18", fc_output_dim=256, short_side=SHORT, device="cpu")
    assert eigen.dim == 256 and eigen.cache_key.startswith("eigenplaces-2.ResNet18-256.s64.")

    folder = tmp_path / "cosplace_weights"
    folder.mkdir()
    (folder / "ResNet18_256_cosplace.pth").write_bytes(path.read_bytes())
    monkeypatch.setenv("VPR_EXPLORER_COSPLACE_WEIGHTS", str(folder))
    cos = get_extractor("cosplace", backbone="ResNet18", fc_output_dim=256, short_side=SHORT, device="cpu")
    batch = np.stack([eigen.load(p) for p in images])
    with torch.no_grad():
        want = official(torch.from_numpy(batch)).numpy()
    np.testing.assert_allclose(eigen.forward(batch), want, atol=2e-5)
    np.testing.assert_allclose(cos.forward(batch), want, atol=2e-5)
    d = extract_descriptors(images, eigen)
    assert d.shape == (4, 256)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)


def test_place_checkpoint_of_another_dimension_or_with_a_missing_key_is_refused(r18_256, tmp_path):
    path, official = r18_256
    with pytest.raises(VPRInputError, match=rf"{path}: is not a ResNet18 512-d GeoLocalizationNet checkpoint "
                                            r"\(wrong shapes: aggregation\.3\.weight is \(256, 512\) where \(512, 512\) "
                                            r"is expected.*the file holds 256-d descriptors: pass fc_output_dim=256"):
        get_extractor("cosplace", backbone="ResNet18", fc_output_dim=512, weights=path)
    state = official.state_dict()
    del state["aggregation.1.p"]
    broken = tmp_path / "no_gem.pth"
    torch.save(state, broken)
    with pytest.raises(VPRInputError, match=r"no_gem\.pth: is not a ResNet18 256-d .*missing keys: aggregation\.1\.p\)"):
        get_extractor("eigenplaces", backbone="ResNet18", fc_output_dim=256, weights=broken)
    training = tmp_path / "last_checkpoint.pth"  # CosPlace's train.py checkpoint layout is accepted too
    torch.save({"epoch_num": 3, "model_state_dict": official.state_dict()}, training)
    assert get_extractor("cosplace", backbone="ResNet18", fc_output_dim=256, weights=training, short_side=SHORT).dim == 256


def test_precision_and_device_options(r18_256, images):
    path, _ = r18_256
    options = dict(backbone="ResNet18", fc_output_dim=256, weights=path, short_side=SHORT, device="cpu")
    fp32 = get_extractor("eigenplaces", **options)
    bf16 = get_extractor("eigenplaces", **options, precision="bf16")
    assert bf16.cache_key == fp32.cache_key + "+bf16"
    batch = np.stack([fp32.load(p) for p in images[:2]])
    close = np.sum(fp32.forward(batch) * bf16.forward(batch), axis=1)
    assert np.all(close > 0.95)  # same descriptor, to bf16's precision
    with pytest.raises(VPRInputError, match="precision='fp16' needs a GPU"):
        get_extractor("eigenplaces", **options, precision="fp16")
    with pytest.raises(VPRInputError, match="precision='int8': choose one of fp32, bf16, fp16"):
        get_extractor("eigenplaces", **options, precision="int8")
    with pytest.raises(VPRInputError, match="device='tpu'"):
        get_extractor("eigenplaces", **{**options, "device": "tpu"})
    if not torch.cuda.is_available():
        with pytest.raises(VPRInputError, match="device='cuda': torch sees no CUDA GPU here"):
            get_extractor("eigenplaces", **{**options, "device": "cuda"})
    with pytest.raises(VPRInputError, match="short_side=8"):
        get_extractor("eigenplaces", **{**options, "short_side": 8})


# ------------------------------------------------------------------ users' own models


class TinyNet(torch.nn.Module):
    """Conv, ReLU, global average pool, linear: ``(B, 3, H, W)`` -> ``(B, 16)``."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 8, 3, padding=1)
        self.fc = torch.nn.Linear(8, 16)

    def forward(self, x):
        return self.fc(torch.relu(self.conv(x)).mean(dim=(2, 3)))


# torch 2.9+ deprecates TorchScript in favour of torch.export; users still have such files.
jit_deprecation = pytest.mark.filterwarnings("ignore:`torch.jit.*` is deprecated:FutureWarning")


def save_torchscript(path: Path, seed: int) -> Path:
    torch.manual_seed(seed)
    torch.jit.save(torch.jit.script(TinyNet().eval()), str(path))
    return path


@pytest.fixture
def forget_registrations():
    names: list[str] = []
    yield names
    for name in names:
        unregister_extractor(name)


@jit_deprecation
def test_torchscript_model_end_to_end_through_the_cache(tmp_path, images, forget_registrations):
    model = save_torchscript(tmp_path / "tiny.pt", seed=0)
    register_extractor("my-ts", model, input_size=(48, 32), normalisation="unit")
    forget_registrations.append("my-ts")
    assert "my-ts" in extractor_names() and available_extractors()["my-ts"] is None
    extractor = get_extractor("my-ts", device="cpu")
    assert extractor.dim == 16 and extractor.load(images[0]).shape == (3, 32, 48)
    assert extractor.cache_key.startswith("my-ts-2.48x32.unit.")

    cache = DescriptorCache(tmp_path / "cache")
    d = extract_descriptors(images, extractor, cache=cache)
    assert d.shape == (4, 16)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    seen: list[tuple[int, int]] = []
    again = extract_descriptors(images, extractor, cache=cache, progress=lambda done, total: seen.append((done, total)))
    np.testing.assert_array_equal(again, d)
    assert seen == [(4, 4)]  # every image came from the cache
    assert cache.stats(extractor.cache_key)["vectors"] == 4

    # A changed model file is another model: new key, new descriptors, nothing stale.
    save_torchscript(model, seed=1)
    os.utime(model, ns=(model.stat().st_atime_ns, model.stat().st_mtime_ns + 1_000_000))
    changed = get_extractor("my-ts", device="cpu")
    assert changed.cache_key != extractor.cache_key
    fresh = extract_descriptors(images, changed, cache=cache)
    assert not np.allclose(fresh, d)

    # A model file that is gone makes the model unavailable, saying which file.
    model.unlink()
    assert "tiny.pt: the model file of model 'my-ts' does not exist" in available_extractors()["my-ts"]


def test_exported_program_model(tmp_path, images, forget_registrations):
    torch.manual_seed(6)
    net = TinyNet().eval()
    batch = torch.export.Dim("batch", min=1, max=1024)
    program = torch.export.export(net, (torch.zeros(2, 3, 32, 32),), dynamic_shapes={"x": {0: batch}})
    torch.export.save(program, str(tmp_path / "tiny.pt2"))
    register_extractor("my-export", tmp_path / "tiny.pt2", input_size=32, dim=16)
    forget_registrations.append("my-export")
    extractor = get_extractor("my-export", device="cpu")
    loaded = np.stack([extractor.load(p) for p in images])
    with torch.no_grad():
        want = net(torch.from_numpy(loaded)).numpy()
    np.testing.assert_allclose(extractor.forward(loaded), want, atol=1e-6)
    assert extract_descriptors(images, extractor).shape == (4, 16)


ENTRY_POINT = '''
import torch

class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        torch.manual_seed(5)
        self.fc = torch.nn.Linear(3, 24)

    def forward(self, x):
        return self.fc(x.mean(dim=(2, 3)))

def build():
    return Net()

def broken():
    raise RuntimeError("weights not found")

def not_a_model():
    return 42
'''


def test_entry_point_models_from_a_file_and_a_module(tmp_path, images, monkeypatch, forget_registrations):
    source = tmp_path / "user_nets.py"
    source.write_text(textwrap.dedent(ENTRY_POINT))
    register_extractor("from-file", f"{source}:build", input_size=40, dim=24)
    monkeypatch.syspath_prepend(str(tmp_path))
    register_extractor("from-module", "user_nets:build", input_size=40)
    forget_registrations.extend(["from-file", "from-module"])

    by_file = get_extractor("from-file", device="cpu")
    by_module = get_extractor("from-module", device="cpu")
    assert by_file.dim == by_module.dim == 24
    d = extract_descriptors(images, by_file)
    np.testing.assert_allclose(d, extract_descriptors(images, by_module), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    assert by_file.cache_key.split("-", 2)[-1] == by_module.cache_key.split("-", 2)[-1]  # same source, same version

    register_extractor("wrong-dim", f"{source}:build", dim=12)
    register_extractor("broken", f"{source}:broken")
    register_extractor("not-a-model", f"{source}:not_a_model")
    forget_registrations.extend(["wrong-dim", "broken", "not-a-model"])
    with pytest.raises(VPRInputError, match="'wrong-dim': returns 24-d descriptors, registered as dim=12"):
        get_extractor("wrong-dim", device="cpu")
    with pytest.raises(VPRInputError, match=r"'broken': the entry point .*:broken failed \(RuntimeError: weights not found\)"):
        get_extractor("broken", device="cpu")
    with pytest.raises(VPRInputError, match="returned int, not a callable"):
        get_extractor("not-a-model", device="cpu")


@jit_deprecation
def test_registration_is_validated(tmp_path, forget_registrations):
    with pytest.raises(VPRInputError, match="name='pixels' is a built-in descriptor"):
        register_extractor("pixels", tmp_path / "x.pt")
    with pytest.raises(VPRInputError, match="name='my net'"):
        register_extractor("my net", tmp_path / "x.pt")
    with pytest.raises(VPRInputError, match="normalisation='bgr': choose one of imagenet, unit, signed"):
        register_extractor("x", tmp_path / "x.pt", normalisation="bgr")
    with pytest.raises(VPRInputError, match=r"input_size=\(224, 0\)"):
        register_extractor("x", tmp_path / "x.pt", input_size=(224, 0))
    text = tmp_path / "notes.pt"
    text.write_text("not torchscript")
    register_extractor("not-ts", text)
    forget_registrations.append("not-ts")
    with pytest.raises(VPRInputError, match=r"notes\.pt: cannot load it as TorchScript .*torch\.jit\.save"):
        get_extractor("not-ts", device="cpu")


@jit_deprecation
def test_models_from_the_settings_file(tmp_path, images, monkeypatch):
    (tmp_path / "nets").mkdir()
    save_torchscript(tmp_path / "nets" / "tiny.pt", seed=4)
    settings = tmp_path / "models.toml"
    settings.write_text(textwrap.dedent('''
        [models.tiny-net]
        model = "nets/tiny.pt"
        input_size = [40, 30]
        normalisation = "signed"
        version = "v2"
    '''))
    monkeypatch.setenv(MODELS_ENV, str(settings))
    assert available_extractors()["tiny-net"] is None
    extractor = get_extractor("tiny-net", device="cpu")
    assert extractor.cache_key.startswith("tiny-net-2.40x30.signed.") and extractor.dim == 16
    assert extract_descriptors(images, extractor).shape == (4, 16)

    settings.write_text('[models.tiny-net]\nmodel = "nets/tiny.pt"\ninput_sise = 40\n')
    with pytest.raises(VPRInputError, match=r"models\.toml: \[models\.tiny-net\] has unknown field\(s\) input_sise"):
        available_extractors()
    settings.write_text('[models.pixels]\nmodel = "nets/tiny.pt"\n')
    with pytest.raises(VPRInputError, match="model name 'pixels' in VPR_EXPLORER_MODELS=.* is a built-in"):
        get_extractor("pixels")
