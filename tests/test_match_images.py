"""paraformer.match_images: one call from two images to a model, and rotated pairs.

The rotated pairs are built from shared photos: a mild random homography, then a turn of
90, 180 or 270° (known ground truth). XFeat's descriptors are upright, so only
``rotations=4`` recovers them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import paraformer
from paraformer.pipeline import unrotate

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "assets" / "sample"
PHOTOS = ROOT.parent / "shared" / "data" / "val" / "bsds500_test"


def turn(k: int, w: int, h: int) -> np.ndarray:
    """Homography of ``np.rot90(img, k)`` on an image ``w × h``: pixel (x, y) → turned pixel."""
    m = np.eye(3)
    for _ in range(k % 4):
        m = np.array([[0, 1, 0], [-1, 0, w - 1], [0, 0, 1]], float) @ m
        w, h = h, w
    return m


def test_match_images_on_the_sample_pair():
    h_true = np.loadtxt(SAMPLE / "H_0to1.txt")
    out = paraformer.match_images(SAMPLE / "coffee_0.jpg", str(SAMPLE / "coffee_1.jpg"))
    assert set(out) == {"keypoints0", "keypoints1", "matches", "scores", "model", "inliers", "rotation"}
    assert out["matches"].shape[1] == 2 and out["matches"].dtype == np.int64 and len(out["scores"]) == len(out["matches"])
    assert out["rotation"] == 0 and out["inliers"].sum() > 100
    assert paraformer.geometry.homography_corner_error(out["model"], h_true, 600, 400) < 3
    nogeo = paraformer.match_images(SAMPLE / "coffee_0.jpg", SAMPLE / "coffee_1.jpg", geometry=None, matcher="mnn")
    assert nogeo["model"] is None and nogeo["inliers"] is None and len(nogeo["matches"]) > 100


def test_match_images_bad_input():
    img = SAMPLE / "coffee_0.jpg"
    with pytest.raises(ValueError, match="rotations"):
        paraformer.match_images(img, img, rotations=2)
    with pytest.raises(ValueError, match="geometry"):
        paraformer.match_images(img, img, geometry="affine")
    with pytest.raises(ValueError, match="threshold"):
        paraformer.match_images(img, img, threshold=-1)
    with pytest.raises(ValueError, match="matcher"):
        paraformer.match_images(img, img, matcher="lightglue")
    with pytest.raises(ValueError, match="image1"):
        paraformer.match_images(img, np.zeros((4, 4, 4, 4)))
    for bad in (np.zeros((64, 64), bool), np.zeros((64, 64), np.complex64), np.full((64, 64), "x")):
        with pytest.raises(ValueError, match=f"image0: expected a path or an integer or float array .* got dtype {bad.dtype}"):
            paraformer.match_images(bad, img)
    with pytest.raises(FileNotFoundError):
        paraformer.match_images(img, SAMPLE / "missing.jpg")


def test_unrotate_inverts_rot90():
    img = np.arange(5 * 7).reshape(5, 7)
    for k in range(4):
        r = np.rot90(img, k)
        ys, xs = np.mgrid[0:r.shape[0], 0:r.shape[1]]
        pts = np.stack([xs.ravel(), ys.ravel()], 1)
        back = np.round(unrotate(pts, k, 7, 5)).astype(int)
        np.testing.assert_array_equal(img[back[:, 1], back[:, 0]], r[pts[:, 1], pts[:, 0]])
        h = turn(k, 7, 5)
        fwd = (h @ np.c_[back, np.ones(len(back))].T).T
        np.testing.assert_allclose(fwd[:, :2] / fwd[:, 2:], pts, atol=1e-9)


def test_rotated_pairs_need_rotations_4():
    if not PHOTOS.is_dir():
        print(f"SKIP: {PHOTOS} is absent")
        pytest.skip(f"{PHOTOS} is absent")
    cv2 = pytest.importorskip("cv2", reason="warping the test pairs needs opencv")
    rng = np.random.default_rng(3)
    photos = sorted(PHOTOS.glob("*.jpg"))[:6]
    ok1 = ok4 = total = 0
    for photo in photos:
        img = paraformer.pipeline.load_image(photo, "photo")
        h, w = img.shape
        corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float32)
        moved = (corners + rng.uniform(-0.06, 0.06, (4, 2)) * [w, h]).astype(np.float32)
        hom = cv2.getPerspectiveTransform(corners, moved).astype(float)
        warped = cv2.warpPerspective(img, hom, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        for k in (1, 2, 3):
            img1 = np.ascontiguousarray(np.rot90(warped, k))
            h_true = turn(k, w, h) @ hom
            total += 1
            for rotations in (1, 4):
                out = paraformer.match_images(img, img1, max_keypoints=1024, rotations=rotations)
                err = (paraformer.geometry.homography_corner_error(out["model"], h_true, w, h)
                       if out["model"] is not None else np.inf)
                if rotations == 1:
                    ok1 += err < 3
                else:
                    ok4 += err < 3
                    assert out["rotation"] == (360 - 90 * k) % 360 or err >= 3
    print(f"rotated pairs recovered within 3 px: rotations=1 {ok1}/{total}, rotations=4 {ok4}/{total}")
    assert ok4 >= 0.9 * total
    assert ok1 <= 0.2 * total


def test_match_images_in_bf16_agrees_with_fp32():
    import paraformer

    a = paraformer.match_images(SAMPLE / "coffee_0.jpg", SAMPLE / "coffee_1.jpg")
    b = paraformer.match_images(SAMPLE / "coffee_0.jpg", SAMPLE / "coffee_1.jpg", precision="bf16")
    pa, pb = {tuple(m) for m in a["matches"].tolist()}, {tuple(m) for m in b["matches"].tolist()}
    assert len(pa & pb) >= 0.97 * len(pa)
    with pytest.raises(ValueError, match="precision"):
        paraformer.match_images(SAMPLE / "coffee_0.jpg", SAMPLE / "coffee_1.jpg", precision="fp64")
