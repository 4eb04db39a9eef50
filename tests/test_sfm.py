"""paraformer.sfm: hloc-format files, resumable stages, pycolmap reconstruction, hloc interop.

Needs the ``sfm`` extra (h5py, pycolmap); hloc's files are read by the vendored hloc in
``../shared/vendor/hloc`` (pure Python); the hloc plug-in test also needs torch.
"""
from __future__ import annotations

import importlib
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import paraformer

h5py = pytest.importorskip("h5py", reason="paraformer.sfm needs h5py (pip install '.[sfm]')")
from paraformer import sfm  # noqa: E402
from paraformer.sfm import io as sfm_io  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "assets" / "sample"
SHARED = ROOT.parent / "shared"
STRECHA = SHARED / "data" / "pose" / "strecha_entry-P10" / "images"
VENDOR_HLOC = SHARED / "vendor" / "hloc"


def _skip(reason: str) -> None:
    print(f"SKIP: {reason}")
    pytest.skip(reason)


def _hloc():
    """The installed hloc, else the vendored source (pure Python) on sys.path."""
    try:
        return importlib.import_module("hloc")
    except ImportError:
        pass
    if not VENDOR_HLOC.is_dir():
        _skip(f"hloc is not installed and {VENDOR_HLOC} is absent")
    for dep in ("cv2", "pycolmap", "tqdm", "packaging"):
        if importlib.util.find_spec(dep) is None:
            _skip(f"hloc's file readers need {dep}")
    sys.path.insert(0, str(VENDOR_HLOC))
    return importlib.import_module("hloc")


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    """Three images, one in a subfolder (names with '/')."""
    d = tmp_path_factory.mktemp("images")
    shutil.copy(SAMPLE / "coffee_0.jpg", d / "a.jpg")
    shutil.copy(SAMPLE / "coffee_1.jpg", d / "b.jpg")
    (d / "sub").mkdir()
    shutil.copy(SAMPLE / "coffee_1.jpg", d / "sub" / "c.jpg")
    (d / "notes.txt").write_text("not an image")
    return d


@pytest.fixture(scope="module")
def features(images, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("feats") / "features.h5"
    sfm.extract(images, path, max_keypoints=512, progress=False)
    return path


def test_pairs_and_pairs_files(tmp_path):
    names = ["a", "b", "c", "d"]
    assert sfm.pairs_exhaustive(names) == [("a", "b"), ("a", "c"), ("a", "d"), ("b", "c"), ("b", "d"), ("c", "d")]
    assert sfm.pairs_sequential(names, 2) == [("a", "b"), ("a", "c"), ("b", "c"), ("b", "d"), ("c", "d")]
    path = sfm.write_pairs(sfm.pairs_exhaustive(names), tmp_path / "pairs.txt")
    assert path.read_text().splitlines()[0] == "a b"
    assert sfm.read_pairs(path) == sfm.pairs_exhaustive(names)
    with pytest.raises(ValueError, match="overlap"):
        sfm.pairs_sequential(names, 0)
    with pytest.raises(ValueError, match="repeated"):
        sfm.pairs_exhaustive(["a", "a"])
    bad = tmp_path / "bad.txt"
    bad.write_text("a b\nc\n")
    with pytest.raises(ValueError, match=r"bad.txt:2"):
        sfm.read_pairs(bad)
    with pytest.raises(ValueError, match="whitespace"):
        sfm.write_pairs([("a b", "c")], tmp_path / "x.txt")


def test_extract_writes_hloc_layout(images, features):
    assert sfm.list_images(images) == ["a.jpg", "b.jpg", "sub/c.jpg"]
    assert sfm_io.list_names(features) == ["a.jpg", "b.jpg", "sub/c.jpg"]
    ref = paraformer.extract(images / "sub" / "c.jpg", max_keypoints=512, subpixel=True)  # sfm's default
    with h5py.File(features, "r") as fd:
        g = fd["sub/c.jpg"]
        n = len(ref["keypoints"])
        assert g["keypoints"].shape == (n, 2) and g["descriptors"].shape == (64, n) and g["scores"].shape == (n,)
        np.testing.assert_array_equal(g["keypoints"][()], ref["keypoints"])
        np.testing.assert_array_equal(g["descriptors"][()], ref["descriptors"].T)
        np.testing.assert_array_equal(g["image_size"][()], [600, 400])


def test_extract_resumes_and_overwrites(images, tmp_path, monkeypatch):
    path = tmp_path / "f.h5"
    sfm.extract(images, path, max_keypoints=256, image_list=["a.jpg"], progress=False)
    calls = []
    real = paraformer.extract
    monkeypatch.setattr(paraformer, "extract", lambda p, **kw: calls.append(p) or real(p, **kw))
    sfm.extract(images, path, max_keypoints=256, progress=False)
    assert sorted(Path(c).name for c in calls) == ["b.jpg", "c.jpg"]  # a.jpg was already there
    calls.clear()
    sfm.extract(images, path, max_keypoints=256, progress=False)
    assert calls == []
    sfm.extract(images, path, max_keypoints=256, overwrite=True, progress=False)
    assert len(calls) == 3
    # Other settings on a resumed file: an error naming both, not a silent mix of the two.
    calls.clear()
    with pytest.raises(ValueError, match='max_keypoints": 256.*max_keypoints": 512'):
        sfm.extract(images, path, max_keypoints=512, progress=False)
    with pytest.raises(ValueError, match="subpixel"):
        sfm.extract(images, path, max_keypoints=256, subpixel=False, progress=False)
    assert calls == []
    sfm.extract(images, path, max_keypoints=512, overwrite=True, progress=False)
    assert len(calls) == 3
    sfm.extract(images, path, max_keypoints=512, progress=False)  # the new settings resume
    assert len(calls) == 3


def test_extract_bad_input(images, tmp_path):
    with pytest.raises(FileNotFoundError, match="not a folder"):
        sfm.extract(tmp_path / "missing", tmp_path / "f.h5")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no images"):
        sfm.extract(tmp_path / "empty", tmp_path / "f.h5")
    with pytest.raises(ValueError, match="max_keypoints"):
        sfm.extract(images, tmp_path / "f.h5", max_keypoints=0)
    with pytest.raises(FileNotFoundError, match="nope.jpg"):
        sfm.extract(images, tmp_path / "f.h5", image_list=["nope.jpg"])
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "x.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ValueError, match="x.jpg"):
        sfm.extract(broken, tmp_path / "g.h5", progress=False)
    # one unreadable file among good ones: a warning naming it, the others extracted
    shutil.copy(SAMPLE / "coffee_0.jpg", broken / "good.jpg")
    with pytest.warns(UserWarning, match="x.jpg"):
        sfm.extract(broken, tmp_path / "h.h5", progress=False)
    assert sfm_io.list_names(tmp_path / "h.h5") == ["good.jpg"]
    # a corrupt or foreign h5 file is named
    bad_h5 = tmp_path / "corrupt.h5"
    bad_h5.write_bytes(b"\x00" * 100)
    with pytest.raises(ValueError, match="corrupt.h5: not a readable HDF5 file"):
        sfm.extract(images, bad_h5, progress=False)
    with pytest.raises(ValueError, match="corrupt.h5: not a readable HDF5 file"):
        sfm.match_pairs(bad_h5, [("a.jpg", "b.jpg")], tmp_path / "m.h5", progress=False)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as fd:
        for n in ("a.jpg", "b.jpg"):
            fd.create_dataset(f"{n}/keypoints", data=np.zeros((3, 2), np.float32))
    with pytest.raises(ValueError, match="has no 'descriptors'"):
        sfm.match_pairs(foreign, [("a.jpg", "b.jpg")], tmp_path / "m2.h5", progress=False)


def test_match_pairs_equals_match_dicts(features, tmp_path):
    pairs = [("a.jpg", "b.jpg"), ("b.jpg", "sub/c.jpg"), ("b.jpg", "a.jpg")]  # the last repeats the first
    out = sfm.match_pairs(features, pairs, tmp_path / "matches.h5", batch=1, progress=False)
    m = paraformer.Matcher.pretrained("paraformer-xfeat")
    with h5py.File(features, "r") as ffd, h5py.File(out, "r") as mfd:
        assert sorted(mfd.keys()) == ["a.jpg", "b.jpg"]  # groups 'a.jpg/b.jpg' and 'b.jpg/sub-c.jpg'
        assert "b.jpg/sub-c.jpg" in mfd and "a.jpg/b.jpg" in mfd
        ref = m.match_dicts(sfm_io.read_features(ffd, "b.jpg"), sfm_io.read_features(ffd, "sub/c.jpg"))
        np.testing.assert_array_equal(mfd["b.jpg/sub-c.jpg/matches0"][()], ref["matches0"])
        np.testing.assert_allclose(mfd["b.jpg/sub-c.jpg/matching_scores0"][()], ref["matching_scores0"], atol=1e-3)
        assert (ref["matches0"] >= 0).sum() > 50
        # reversed lookup flips the index pairs
        fwd, _ = sfm_io.read_matches(mfd, "b.jpg", "sub/c.jpg")
        rev, _ = sfm_io.read_matches(mfd, "sub/c.jpg", "b.jpg")
        np.testing.assert_array_equal(fwd, rev[:, ::-1])


def test_match_pairs_resumes_and_checks(features, tmp_path, monkeypatch):
    path = tmp_path / "m.h5"
    sfm.match_pairs(features, [("a.jpg", "b.jpg")], path, progress=False)
    calls = []
    real = paraformer.Matcher.match_many
    monkeypatch.setattr(paraformer.Matcher, "match_many", lambda self, p, **kw: calls.append(len(p)) or real(self, p, **kw))
    pairs_file = sfm.write_pairs([("a.jpg", "b.jpg"), ("a.jpg", "sub/c.jpg")], tmp_path / "pairs.txt")
    sfm.match_pairs(features, pairs_file, path, progress=False)
    assert calls == [1]  # only the new pair
    with pytest.raises(ValueError, match="holds matches of 'paraformer-xfeat'"):
        sfm.match_pairs(features, pairs_file, path, matcher="mnn", progress=False)
    sfm.match_pairs(features, pairs_file, tmp_path / "mnn.h5", matcher="mnn", progress=False)
    with pytest.raises(KeyError, match="missing.jpg"):
        sfm.match_pairs(features, [("a.jpg", "missing.jpg")], tmp_path / "x.h5", progress=False)
    with pytest.raises(ValueError, match="not a pretrained name"):
        sfm.match_pairs(features, [("a.jpg", "b.jpg")], tmp_path / "y.h5", matcher="superglue-outdoor", progress=False)
    with pytest.raises(ValueError, match="itself"):
        sfm.match_pairs(features, [("a.jpg", "a.jpg")], tmp_path / "z.h5", progress=False)
    with pytest.raises(FileNotFoundError, match="features_path"):
        sfm.match_pairs(tmp_path / "none.h5", [("a.jpg", "b.jpg")], tmp_path / "z.h5", progress=False)
    # No pairs would write no file, which the next step fails to open: named instead. A bad
    # backend is named even when every pair is already done.
    (tmp_path / "empty.txt").write_text("")
    with pytest.raises(ValueError, match=r"^pairs: no pairs in .*empty.txt"):
        sfm.match_pairs(features, tmp_path / "empty.txt", tmp_path / "e.h5", progress=False)
    with pytest.raises(ValueError, match=r"^pairs: no pairs in the list"):
        sfm.match_pairs(features, [], tmp_path / "e.h5", progress=False)
    with pytest.raises(ValueError, match=r"^backend: "):
        sfm.match_pairs(features, pairs_file, path, progress=False, backend="spark")


def test_reconstruct_bad_input(images, tmp_path):
    pytest.importorskip("pycolmap", reason="reconstruct needs pycolmap (pip install '.[sfm]')")
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(SAMPLE / "coffee_0.jpg", one / "a.jpg")
    with pytest.raises(ValueError, match="at least 2 images"):
        sfm.reconstruct(one, tmp_path / "o1", progress=False)
    pairs = sfm.write_pairs([("a.jpg", "missing.jpg")], tmp_path / "p.txt")
    with pytest.raises(ValueError, match="missing.jpg"):
        sfm.reconstruct(images, tmp_path / "o2", pairs=pairs, progress=False)
    with pytest.raises(ValueError, match="camera_mode"):
        sfm.reconstruct(images, tmp_path / "o3", camera_mode="fisheye", progress=False)
    with pytest.raises(ValueError, match="sequential:N"):
        sfm.reconstruct(images, tmp_path / "o4", pairs="sequential:0", progress=False)


def test_cli_pairs_and_errors(images, tmp_path):
    run = [sys.executable, "-m", "paraformer.sfm"]
    r = subprocess.run(run + ["pairs", str(images), str(tmp_path / "p.txt"), "--pairs", "sequential:1"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert sfm.read_pairs(tmp_path / "p.txt") == [("a.jpg", "b.jpg"), ("b.jpg", "sub/c.jpg")]
    r = subprocess.run(run + ["extract", str(tmp_path / "nothing"), str(tmp_path / "f.h5")], capture_output=True, text=True)
    assert r.returncode == 1 and "not a folder" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(run + ["match", str(tmp_path / "f.h5"), str(tmp_path / "p.txt"), str(tmp_path / "m.h5")],
                       capture_output=True, text=True)
    assert r.returncode == 1 and "features_path" in r.stderr


def _strecha(tmp_path: Path, n: int) -> Path:
    if not STRECHA.is_dir():
        _skip(f"{STRECHA} is absent")
    d = tmp_path / "strecha"
    d.mkdir()
    for p in sorted(STRECHA.glob("*.jpg"))[:n]:
        shutil.copy(p, d / p.name)
    return d


def test_reconstruct_strecha(tmp_path):
    pycolmap = pytest.importorskip("pycolmap", reason="reconstruct needs pycolmap (pip install '.[sfm]')")
    images = _strecha(tmp_path, 5)
    cv2 = pytest.importorskip("cv2", reason="the mixed-size case needs opencv")
    # mixed image sizes: one image at 3/4 size, and one unreadable file to be skipped
    small = cv2.imread(str(images / "0004.jpg"))
    cv2.imwrite(str(images / "0004.jpg"), cv2.resize(small, None, fx=0.75, fy=0.75, interpolation=cv2.INTER_AREA))
    (images / "zz_corrupt.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match="zz_corrupt.jpg"):
        rec = sfm.reconstruct(images, out, max_keypoints=1024, progress=False)
    assert rec is not None and rec.num_reg_images() >= 4 and rec.num_points3D() > 200
    assert len({c.width for c in rec.cameras.values()}) == 2  # one camera per image size
    for f in ("features.h5", "pairs.txt", "matches.h5", "database.db", "summary.json", "sparse/0/images.bin"):
        assert (out / f).exists(), f
    back = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert back.num_reg_images() == rec.num_reg_images()
    import json

    s = json.loads((out / "summary.json").read_text())
    assert s["registered_images"] == rec.num_reg_images() and 0 < s["mean_reprojection_error_px"] < 2
    assert set(s["seconds"]) >= {"extract_s", "match_s", "import_s", "verification_s", "mapping_s"}
    # A rerun from the files alone (seeded like the first; COLMAP's threads can still make
    # the two models differ in a few points).
    again = sfm.reconstruct_from_files(images, tmp_path / "again", out / "features.h5", out / "pairs.txt",
                                       out / "matches.h5")
    assert again.num_reg_images() == rec.num_reg_images()
    assert abs(again.num_points3D() - rec.num_points3D()) < 0.25 * rec.num_points3D()


def test_hloc_reads_our_files_and_we_read_hlocs(tmp_path):
    pytest.importorskip("pycolmap", reason="needs pycolmap")
    hloc = _hloc()
    from hloc import reconstruction as hloc_rec
    from hloc.utils.io import get_keypoints, get_matches

    images = _strecha(tmp_path, 4)
    feats, matches = tmp_path / "features.h5", tmp_path / "matches.h5"
    sfm.extract(images, feats, max_keypoints=1024, progress=False)
    pairs = sfm.write_pairs(sfm.pairs_exhaustive(sfm.list_images(images)), tmp_path / "pairs.txt")
    sfm.match_pairs(feats, pairs, matches, matcher="mnn", progress=False)
    # hloc's readers on our files
    np.testing.assert_array_equal(get_keypoints(feats, "0000.jpg"), paraformer.extract(images / "0000.jpg", 1024, subpixel=True)["keypoints"])
    with h5py.File(matches, "r") as fd:
        ours, _ = sfm_io.read_matches(fd, "0001.jpg", "0000.jpg")
    theirs, _ = get_matches(matches, "0001.jpg", "0000.jpg")
    np.testing.assert_array_equal(ours, theirs)
    # hloc's reconstruction on our files
    rec = hloc_rec.main(tmp_path / "hloc_sfm", images, pairs, feats, matches)
    assert rec is not None and rec.num_reg_images() >= 3, hloc.__file__
    # a matches file in hloc's older pair naming, read by our reconstruction
    old = tmp_path / "matches_old.h5"
    with h5py.File(matches, "r") as src, h5py.File(old, "w") as dst:
        for a, b in sfm.read_pairs(pairs):
            g = dst.create_group(sfm_io.names_to_pair_old(b, a))  # stored reversed, '_' naming
            m, s = sfm_io.read_matches(src, a, b)
            m0 = np.full(len(get_keypoints(feats, b)), -1, np.int16)
            m0[m[:, 1]] = m[:, 0]
            g.create_dataset("matches0", data=m0)
            g.create_dataset("matching_scores0", data=np.ones(len(m0), np.float16))
    ours_rec = sfm.reconstruct_from_files(images, tmp_path / "ours", feats, pairs, old)
    assert ours_rec is not None and ours_rec.num_reg_images() >= 3


def test_hloc_plugin_matches_like_match_pairs(features, tmp_path):
    pytest.importorskip("pycolmap", reason="hloc needs pycolmap")
    try:
        import torch  # noqa: F401
    except ImportError:
        _skip("the hloc plug-in test needs torch")
    _hloc()
    from hloc import match_features
    from paraformer.sfm import hloc_plugin

    hloc_plugin.register()
    pairs = sfm.write_pairs([("a.jpg", "b.jpg"), ("b.jpg", "sub/c.jpg")], tmp_path / "pairs.txt")
    theirs = tmp_path / "hloc_matches.h5"
    match_features.main(hloc_plugin.confs["paraformer-xfeat"], pairs, features=features, matches=theirs)
    ours = sfm.match_pairs(features, pairs, tmp_path / "ours.h5", progress=False)
    with h5py.File(theirs, "r") as t, h5py.File(ours, "r") as o:
        for a, b in sfm.read_pairs(pairs):
            mt, _ = sfm_io.read_matches(t, a, b)
            mo, _ = sfm_io.read_matches(o, a, b)
            np.testing.assert_array_equal(mt, mo)
            assert len(mo) > 50
