"""JPEGs decoded and resized on the model's device (``decode="device"``): on CPU tensors, or on the
device ``VPR_EXPLORER_TEST_DEVICE`` names (``benchmarks/gpu_check.py`` sets it to the GPU).

The device path must give the CPU path's descriptors: within a cosine of 0.9999 per image
on real GardensPoint frames (EfficientNet-Lite0, and a CosPlace network with random
weights on frames of two aspects), exactly for files it leaves to the CPU (a PNG, a CMYK
JPEG), exactly in its normalisation (no resize: the inputs are bit-identical), within one
level of PIL's bilinear resize, with the same errors for a truncated file, and into the
same cache key. Files are told apart by their bytes: a hand-made marker walk is checked too.
"""

from __future__ import annotations

import io
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from vpr_explorer.descriptors import DescriptorCache, extract_descriptors, get_extractor
from vpr_explorer.descriptors import device_decode
from vpr_explorer.descriptors.device_decode import (
    DeviceRecipe,
    device_decodable,
    read_source,
    resize_and_normalise,
    resize_levels,
    use_device,
)
from vpr_explorer.descriptors.efficientnet import to_unit_range
from vpr_explorer.descriptors.preprocess import Normalisation
from vpr_explorer.errors import VPRInputError

# torchvision 0.29 warns that its decoders move to TorchCodec, on every call
pytestmark = pytest.mark.filterwarnings("ignore:The image decoding and encoding capabilities:DeprecationWarning")

MIN_COSINE = 0.9999  # CPU vs GPU descriptors: one cache key
N_IMAGES = 24


@pytest.fixture(scope="module")
def gp_jpegs(data_root) -> list[Path]:
    """24 GardensPoint frames (960 x 540 JPEGs), spread over the three traversals."""
    paths = sorted((data_root / "GardensPointWalking").glob("*/*.jpg"))
    assert len(paths) == 600
    return paths[:: len(paths) // N_IMAGES][:N_IMAGES]


@pytest.fixture(scope="module")
def effnet(device_under_test):
    return get_extractor("efficientnet-lite0", device=device_under_test)


def cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a.astype(np.float64) * b.astype(np.float64), axis=1)


def save_as(source: Path, path: Path, fmt: str, mode: str = "RGB", crop: tuple[int, int, int, int] | None = None,
            **options) -> Path:
    with Image.open(source) as image:
        picture = image.convert(mode)
    if crop is not None:
        picture = picture.crop(crop)
    picture.save(path, fmt, **options)
    return path


# ------------------------------------------------------------------ descriptors against the CPU path


@pytest.mark.realdata
def test_efficientnet_on_gardens_point_is_the_cpu_path(gp_jpegs, effnet):
    cpu = extract_descriptors(gp_jpegs, effnet, decode="cpu", batch_size=16)
    device = extract_descriptors(gp_jpegs, effnet, decode="device", batch_size=16)
    c = cosines(cpu, device)
    worst = int(np.argmin(c))
    assert c.min() > MIN_COSINE, f"{gp_jpegs[worst]}: cosine {c[worst]:.6f}"
    assert not np.array_equal(cpu, device)  # the device path ran: its resize differs in a few levels


@pytest.mark.realdata
def test_short_side_recipe_on_jpegs_of_two_aspects(gp_jpegs, tmp_path, device_under_test):
    from vpr_explorer.descriptors.gem_resnet import GeoLocalizationNet

    torch.manual_seed(0)
    weights = tmp_path / "ResNet18_256_cosplace.pth"
    torch.save(GeoLocalizationNet("ResNet18", 256).state_dict(), weights)
    extractor = get_extractor("cosplace", backbone="ResNet18", fc_output_dim=256, weights=weights, short_side=64,
                              device=device_under_test)
    assert extractor.recipe == DeviceRecipe(normalisation=Normalisation.IMAGENET, short_side=64)
    # landscape 960 x 540 frames and portrait 360 x 540 crops of others, interleaved in one batch
    portrait = [save_as(p, tmp_path / f"portrait{i}.jpg", "JPEG", crop=(300, 0, 660, 540), quality=90)
                for i, p in enumerate(gp_jpegs[1:8:2])]
    paths = [p for pair in zip(gp_jpegs[0:8:2], portrait) for p in pair]
    assert {extractor.load(p).shape for p in paths} == {(3, 64, 113), (3, 96, 64)}
    cpu = extract_descriptors(paths, extractor, decode="cpu", batch_size=8)
    device = extract_descriptors(paths, extractor, decode="device", batch_size=8)
    assert cosines(cpu, device).min() > MIN_COSINE


@pytest.mark.realdata
def test_a_png_and_a_cmyk_jpeg_take_the_cpu_path_and_give_its_rows_exactly(gp_jpegs, effnet, tmp_path, monkeypatch):
    png = save_as(gp_jpegs[1], tmp_path / "frame.png", "PNG")
    cmyk = save_as(gp_jpegs[2], tmp_path / "cmyk.jpg", "JPEG", mode="CMYK", quality=95)
    paths = [gp_jpegs[0], png, cmyk, gp_jpegs[3]]
    decoded = []
    real = device_decode.decode_jpegs
    monkeypatch.setattr(device_decode, "decode_jpegs",
                        lambda data, names, extractor: decoded.extend(names) or real(data, names, extractor))
    cpu = extract_descriptors(paths, effnet, decode="cpu", batch_size=4)
    device = extract_descriptors(paths, effnet, decode="device", batch_size=4)
    assert decoded == [gp_jpegs[0], gp_jpegs[3]]
    np.testing.assert_array_equal(device[1:3], cpu[1:3])  # same inputs, same batch: bit-identical rows
    assert cosines(cpu, device).min() > MIN_COSINE


@pytest.mark.realdata
def test_without_resize_the_inputs_are_the_cpu_inputs_bit_for_bit(gp_jpegs):
    from torchvision.io import ImageReadMode, decode_jpeg

    for normalisation in (Normalisation.IMAGENET, Normalisation.UNIT, to_unit_range):
        recipe = DeviceRecipe(normalisation=normalisation, size=(960, 540))
        data = gp_jpegs[5].read_bytes()
        pixels = decode_jpeg(torch.frombuffer(bytearray(data), dtype=torch.uint8), mode=ImageReadMode.RGB)
        got = resize_and_normalise([pixels], recipe)[0]
        np.testing.assert_array_equal(got.numpy(), recipe.load(gp_jpegs[5]))


@pytest.mark.realdata
def test_resize_is_pils_bilinear_within_one_level(gp_jpegs):
    with Image.open(gp_jpegs[7]) as image:
        rgb = image.convert("RGB")
    x = torch.from_numpy(np.asarray(rgb).transpose(2, 0, 1).copy())[None]
    for recipe in (DeviceRecipe(Normalisation.UNIT, size=(224, 224)), DeviceRecipe(Normalisation.UNIT, short_side=64)):
        size = recipe.output_size(rgb.width, rgb.height)
        want = np.asarray(rgb.resize(size, Image.BILINEAR)).transpose(2, 0, 1).astype(np.int16)
        got = resize_levels(x, recipe)[0].numpy()
        assert got.shape == want.shape and np.all(got == np.round(got))
        diff = np.abs(got.astype(np.int16) - want)
        assert diff.max() <= 1 and np.count_nonzero(diff) < 0.01 * diff.size


# ------------------------------------------------------------------ errors, choices, cache


@pytest.mark.realdata
def test_a_truncated_jpeg_raises_what_the_cpu_path_raises(gp_jpegs, effnet, tmp_path):
    broken = tmp_path / "broken.jpg"
    data = gp_jpegs[0].read_bytes()
    broken.write_bytes(data[: len(data) // 2])
    messages = []
    for decode in ("cpu", "device"):
        with pytest.raises(VPRInputError, match="broken.jpg: cannot read the image") as err:
            extract_descriptors([gp_jpegs[1], broken], effnet, decode=decode)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and str(broken) in messages[0]


def test_decode_choices_are_checked_by_name(effnet, tmp_path):
    image = tmp_path / "a.png"
    Image.new("RGB", (32, 24), (10, 200, 30)).save(image)
    with pytest.raises(VPRInputError, match=r"decode='device': descriptor 'pixels' has no device recipe"):
        extract_descriptors([image], get_extractor("pixels"), decode="device")
    with pytest.raises(VPRInputError, match=r"decode='gpu': choose one of auto, cpu, device"):
        extract_descriptors([image], effnet, decode="gpu")
    # auto: the device path only for a recipe on CUDA
    assert not use_device("auto", effnet) and use_device("device", effnet)
    assert not use_device("auto", get_extractor("pixels"))
    on_gpu = SimpleNamespace(name="x", recipe=effnet.recipe, device=torch.device("cuda", 0))
    assert use_device("auto", on_gpu) and not use_device("cpu", on_gpu)


@pytest.mark.realdata
def test_a_device_run_fills_the_cache_a_cpu_run_reads(gp_jpegs, effnet, tmp_path):
    cache = DescriptorCache(tmp_path / "cache")
    paths = gp_jpegs[:6]
    device = extract_descriptors(paths, effnet, cache=cache, decode="device")
    first = []
    again = extract_descriptors(paths, effnet, cache=cache, decode="cpu",
                                progress=lambda done, total: first.append(done) if not first else None)
    assert first == [len(paths)]  # every image found in the cache
    np.testing.assert_array_equal(again, device)


# ------------------------------------------------------------------ telling files apart


def jpeg_bytes(mode: str = "RGB", **options) -> bytes:
    buffer = io.BytesIO()
    Image.new(mode, (16, 8), "white" if mode != "CMYK" else (0, 0, 0, 0)).save(buffer, "JPEG", **options)
    return buffer.getvalue()


def test_device_decodable_reads_the_frame_header():
    assert device_decodable(jpeg_bytes())
    assert device_decodable(jpeg_bytes("L"))
    assert device_decodable(jpeg_bytes(progressive=True))
    assert not device_decodable(jpeg_bytes("CMYK"))  # 4 components
    whole = jpeg_bytes()
    assert not device_decodable(whole[:-2])  # no end-of-image marker: truncated
    assert not device_decodable(whole[:40] + b"\xff\xd9")  # the frame header cut off
    png = io.BytesIO()
    Image.new("RGB", (4, 4)).save(png, "PNG")
    assert not device_decodable(png.getvalue())
    assert not device_decodable(b"")
    # hand-made: SOI, a 12-bit baseline frame (precision 12), EOI; then the same at 8 bits
    frame = bytes([0xFF, 0xC0, 0x00, 0x11, 12, 0x00, 0x08, 0x00, 0x10, 3]) + bytes(9)
    assert not device_decodable(b"\xff\xd8" + frame + b"\xff\xd9")
    assert device_decodable(b"\xff\xd8" + frame[:4] + bytes([8]) + frame[5:] + b"\xff\xd9")
    # an arithmetic-coded frame (C9) and a scan before any frame
    assert not device_decodable(b"\xff\xd8" + bytes([0xFF, 0xC9]) + frame[2:] + b"\xff\xd9")
    assert not device_decodable(b"\xff\xd8\xff\xda\x00\x02\xff\xd9")


def test_read_source_gives_bytes_for_a_jpeg_and_the_loaded_image_otherwise(effnet, tmp_path):
    jpeg, png = tmp_path / "a.dat", tmp_path / "b.jpg"  # the bytes decide, not the name
    jpeg.write_bytes(jpeg_bytes())
    Image.new("RGB", (16, 8), "white").save(png, "PNG")
    got = read_source(jpeg, effnet)
    assert isinstance(got, torch.Tensor) and got.dtype == torch.uint8 and bytes(got.numpy()) == jpeg.read_bytes()
    np.testing.assert_array_equal(read_source(png, effnet), effnet.load(png))
    with pytest.raises(VPRInputError, match="missing.jpg: the image file does not exist"):
        read_source(tmp_path / "missing.jpg", effnet)


def test_a_recipe_gives_exactly_one_resize():
    with pytest.raises(VPRInputError, match="exactly one"):
        DeviceRecipe(Normalisation.IMAGENET)
    with pytest.raises(VPRInputError, match="exactly one"):
        DeviceRecipe(Normalisation.IMAGENET, size=(4, 4), short_side=4)
    assert DeviceRecipe(Normalisation.IMAGENET, short_side=480).output_size(960, 540) == (853, 480)
    assert DeviceRecipe(Normalisation.IMAGENET, size=[322, 320]).size == (322, 320)


# ------------------------------------------------------------------ command line


@pytest.mark.realdata
def test_extract_decode_flag_fills_one_cache_and_is_refused_for_pixels(gp_jpegs, tmp_path, capsys):
    from cli_run import assert_one_error_line, refused

    root = tmp_path / "route"
    for t, traversal in enumerate(("a", "b")):
        (root / traversal).mkdir(parents=True)
        for f in range(3):
            (root / traversal / f"{f:03d}.jpg").write_bytes(gp_jpegs[6 * t + f].read_bytes())
    cache = str(tmp_path / "cache")
    common = ("extract", "--dataset", str(root), "--cache-dir", cache, "--descriptor", "efficientnet-lite0")
    first = refused(capsys, *common, "--decode", "device")
    assert first.returncode == 0, first.stderr[-1000:]
    assert first.stdout.strip().splitlines()[-1].startswith("6 images: 0 already cached")
    second = refused(capsys, *common, "--decode", "cpu")
    assert second.stdout.strip().splitlines()[-1].startswith("6 images: 6 already cached")
    r = refused(capsys, "extract", "--dataset", str(root), "--cache-dir", cache, "--descriptor", "pixels",
                "--decode", "device")
    assert_one_error_line(r, "decode='device'", "'pixels'", alone=False)
    r = refused(capsys, *common, "--decode", "cpu", "--ray", "local")
    assert_one_error_line(r, "--decode applies to local extraction only")
