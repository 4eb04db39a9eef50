"""paraformer.extract (XFeat in Rust) from Python: parity with the PyTorch original's
fixtures (tests/data/xfeat, from scripts/make_xfeat_fixtures.py), array and path inputs,
bad inputs, and the extract → match_dicts pipeline."""
from pathlib import Path

import numpy as np
import pytest

import paraformer

from conftest import DATA, load_case

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "assets" / "sample"
FIXTURES = ["coffee_crop_rgb", "coffee_warped_rgb", "rocket_gray"]


def _png(path: Path) -> np.ndarray:
    cv2 = pytest.importorskip("cv2")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return img[:, :, ::-1].copy() if img.ndim == 3 else img


def _agreement(ours: dict, ref: dict) -> tuple[float, float]:
    k0, k1 = ref["keypoints"], ours["keypoints"]
    d = np.linalg.norm(k0[:, None] - k1[None], axis=2)
    j = d.argmin(1)
    hit = d[np.arange(len(k0)), j] <= 0.5
    cos = (ref["descriptors"][hit] * ours["descriptors"][j[hit]]).sum(1)
    return hit.mean(), cos.min()


@pytest.mark.parametrize("name", FIXTURES)
def test_extract_matches_pytorch_xfeat_from_path(name):
    """Tolerances of issue 6: ≥ 99% of keypoints within 0.5 px, descriptor cosine ≥ 0.999."""
    ref = load_case(DATA / "xfeat" / f"{name}.safetensors")
    ours = paraformer.extract(DATA / "xfeat" / f"{name}.png", max_keypoints=1024)
    assert len(ours["keypoints"]) == len(ref["keypoints"])
    frac, cos = _agreement(ours, ref)
    assert frac >= 0.99 and cos >= 0.999, (frac, cos)


def test_extract_from_arrays_equals_from_path():
    path = DATA / "xfeat" / "rocket_gray.png"
    img = _png(path)
    a = paraformer.extract(path, 300)
    for arr in (img, img.astype(np.float32), img[:, :, None], np.repeat(img[:, :, None], 3, 2),
                np.concatenate([np.repeat(img[:, :, None], 3, 2), np.full(img.shape + (1,), 7, np.uint8)], 2)):
        b = paraformer.extract(arr, max_keypoints=300)
        np.testing.assert_array_equal(a["keypoints"], b["keypoints"])
        np.testing.assert_allclose(a["descriptors"], b["descriptors"], atol=1e-6)
    assert a["keypoints"].dtype == np.float32 and a["descriptors"].shape == (300, 64)
    np.testing.assert_allclose(np.linalg.norm(a["descriptors"], axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(a["image_size"], [img.shape[1], img.shape[0]])
    assert (np.diff(a["scores"]) <= 0).all()


def test_extract_uint8_colour_equals_float_and_other_integers():
    """uint8 pixels go to Rust as bytes, other types as float32: the same keypoints."""
    img = _png(DATA / "xfeat" / "coffee_crop_rgb.png")
    a = paraformer.extract(img, 500)
    for arr in (img.astype(np.float32), img.astype(np.int32), img.astype(np.float64)):
        b = paraformer.extract(arr, 500)
        np.testing.assert_array_equal(a["keypoints"], b["keypoints"])
        np.testing.assert_array_equal(a["descriptors"], b["descriptors"])
    # A 16-bit copy (0–65535): XFeat's instance norm removes the scale.
    c = paraformer.extract(img.astype(np.uint16) * 257, 500)
    np.testing.assert_array_equal(a["keypoints"], c["keypoints"])
    np.testing.assert_allclose(a["descriptors"], c["descriptors"], atol=1e-5)


def test_native_extract_rejects_an_unknown_pixel_type():
    from paraformer._paraformer import extract as native_extract

    with pytest.raises(ValueError, match="dtype.*u16"):
        native_extract(bytes(64 * 64), 64, 64, 1, 10, "u16")
    with pytest.raises(ValueError, match="image"):
        native_extract(bytes(10), 64, 64, 1, 10, "u8")


def test_extract_then_match_recovers_the_sample_homography():
    f0 = paraformer.extract(SAMPLE / "coffee_0.jpg", 512)
    f1 = paraformer.extract(str(SAMPLE / "coffee_1.jpg"), 512)
    m0 = paraformer.geometry.match_baseline(f0["descriptors"], f1["descriptors"], "mnn")
    ok = m0 >= 0
    fit = paraformer.geometry.find_homography(f0["keypoints"][ok], f1["keypoints"][m0[ok]], threshold=3.0)
    h_true = np.loadtxt(SAMPLE / "H_0to1.txt")
    err = paraformer.geometry.homography_corner_error(fit["model"], h_true, 600, 400)
    assert fit["inliers"].sum() > 100 and err < 3.0, err
    if paraformer.pretrained_names():
        out = paraformer.Matcher.pretrained().match_dicts(f0, f1)
        assert (out["matches0"] >= 0).sum() > 100


@pytest.mark.parametrize("image, needle", [
    (np.zeros((20, 100), np.uint8), "at least 32×32"),
    (np.zeros((64, 64, 5), np.uint8), "C in 1..4"),
    (np.zeros((2, 64, 64, 3), np.uint8), "[H, W] or [H, W, C]"),
    (np.zeros((64, 64), bool), "dtype bool"),
    (np.array([["a"] * 40] * 40), "dtype"),
    (np.full((64, 64), np.nan, np.float32), "NaN"),
])
def test_extract_bad_arrays_name_the_problem(image, needle):
    with pytest.raises(ValueError, match="image") as e:
        paraformer.extract(image)
    assert needle in str(e.value)


def test_extract_bad_paths_and_arguments(tmp_path):
    with pytest.raises(FileNotFoundError, match="no_such.png"):
        paraformer.extract(tmp_path / "no_such.png")
    junk = tmp_path / "junk.jpg"
    junk.write_bytes(b"\xff\xd8 not really a jpeg")
    with pytest.raises(ValueError, match="unreadable image"):
        paraformer.extract(junk)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="max_keypoints"):
            paraformer.extract(np.zeros((64, 64), np.uint8), max_keypoints=bad)
    flat = paraformer.extract(np.full((64, 64), 90, np.uint8))
    assert flat["keypoints"].shape == (0, 2) and flat["descriptors"].shape == (0, 64)


def test_pretrained_unknown_name_lists_the_known_ones():
    with pytest.raises(ValueError, match="no pretrained matcher `nope`"):
        paraformer.Matcher.pretrained("nope")
    with pytest.raises(ValueError, match="name"):
        paraformer.Matcher.pretrained(3)


def test_subpixel_keypoints_refine_within_half_a_pixel():
    a = paraformer.extract(SAMPLE / "coffee_0.jpg", 400)
    b = paraformer.extract(SAMPLE / "coffee_0.jpg", 400, subpixel=True)
    np.testing.assert_array_equal(a["scores"], b["scores"])
    shift = np.abs(a["keypoints"] - b["keypoints"])
    scale = np.array([600 / 576, 400 / 384])  # the sample is resized to multiples of 32
    assert (shift <= 0.5 * scale + 1e-4).all() and (shift > 0).any(axis=1).mean() > 0.5
    np.testing.assert_allclose(np.linalg.norm(b["descriptors"], axis=1), 1.0, atol=1e-5)
