"""backend="ray" on a local Ray: identical files to the local backend, a killed worker, resuming.

Needs the ``ray`` extra (``pip install '.[ray]'``) and h5py; skipped with a printed reason
otherwise. Ray runs with 2 CPUs and a small object store.
"""
from __future__ import annotations

import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

h5py = pytest.importorskip("h5py", reason="paraformer.sfm needs h5py (pip install '.[sfm]')")
ray = pytest.importorskip("ray", reason="the Ray backend needs ray (pip install '.[ray]')")
from paraformer import sfm  # noqa: E402
from paraformer.sfm import io as sfm_io  # noqa: E402

SAMPLE = Path(__file__).resolve().parents[1] / "assets" / "sample"


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=200 * 2**20,
             log_to_driver=False, configure_logging=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def collection(tmp_path_factory) -> tuple[Path, Path, list]:
    """Eight images (the sample pair, renamed), their local features and 28 pairs."""
    d = tmp_path_factory.mktemp("images")
    for i in range(8):
        shutil.copy(SAMPLE / f"coffee_{i % 2}.jpg", d / f"img{i}.jpg")
    feats = d.parent / "features_local.h5"
    sfm.extract(d, feats, max_keypoints=512, progress=False)
    return d, feats, sfm.pairs_exhaustive(sfm.list_images(d))


def _same_h5(a: Path, b: Path) -> None:
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        def items(f):
            out = {}
            f.visititems(lambda n, o: out.__setitem__(n, o[()]) if isinstance(o, h5py.Dataset) else None)
            return out
        ia, ib = items(fa), items(fb)
        assert sorted(ia) == sorted(ib)
        for k in ia:
            assert ia[k].dtype == ib[k].dtype and np.array_equal(ia[k], ib[k]), k


def test_extract_ray_equals_local(collection, tmp_path):
    images, feats, _ = collection
    out = sfm.extract(images, tmp_path / "f.h5", max_keypoints=512, progress=False, backend="ray",
                      num_workers=2, threads_per_worker=1)
    _same_h5(feats, out)


def _match_worker_pids() -> list[int]:
    pids = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if b"MatchWorker" in (p / "cmdline").read_bytes():
                    pids.append(int(p.name))
            except OSError:
                pass
    return pids


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds the actor process through /proc")
def test_match_ray_equals_local_and_survives_a_killed_worker(collection, tmp_path):
    _, feats, pairs = collection
    local = sfm.match_pairs(feats, pairs, tmp_path / "local.h5", progress=False)
    killed = []

    def kill_one(done: int) -> None:
        if not killed:
            pids = _match_worker_pids()
            assert pids, "no MatchWorker actor process found"
            os.kill(pids[0], signal.SIGKILL)
            killed.append(pids[0])

    out = sfm.match_pairs(feats, pairs, tmp_path / "ray.h5", batch=2, progress=False, backend="ray",
                          num_workers=2, threads_per_worker=1, on_batch=kill_one)
    assert killed, "the run ended before a worker could be killed"
    _same_h5(local, out)


def test_interrupted_ray_run_resumes(collection, tmp_path):
    _, feats, pairs = collection
    local = sfm.match_pairs(feats, pairs, tmp_path / "local.h5", progress=False)

    class Stop(Exception):
        pass

    def stop(done: int) -> None:
        if done >= 4:
            raise Stop

    path = tmp_path / "ray.h5"
    with pytest.raises(Stop):
        sfm.match_pairs(feats, pairs, path, batch=2, progress=False, backend="ray", num_workers=1,
                        threads_per_worker=1, on_batch=stop)
    with h5py.File(path, "r") as fd:
        partial = sum(sfm_io.has_pair(fd, a, b) for a, b in pairs)
    assert 4 <= partial < len(pairs)
    sfm.match_pairs(feats, pairs, path, batch=2, progress=False, backend="ray", num_workers=1, threads_per_worker=1)
    _same_h5(local, path)


def test_ray_bad_options(collection, tmp_path):
    _, feats, pairs = collection
    with pytest.raises(ValueError, match="num_workers"):
        sfm.match_pairs(feats, pairs, tmp_path / "x.h5", backend="ray", num_workers=0, progress=False)
    with pytest.raises(ValueError, match="threads_per_worker"):
        sfm.match_pairs(feats, pairs, tmp_path / "x.h5", backend="ray", threads_per_worker=0, progress=False)
    with pytest.raises(ValueError, match="backend"):
        sfm.match_pairs(feats, pairs, tmp_path / "x.h5", backend="dask", progress=False)
    with pytest.raises(TypeError, match="backend='ray'"):
        sfm.match_pairs(feats, pairs, tmp_path / "x.h5", num_workers=2, progress=False)
    import paraformer

    with pytest.raises(ValueError, match="not a Matcher object"):
        sfm.match_pairs(feats, pairs, tmp_path / "x.h5", backend="ray", progress=False,
                        matcher=paraformer.Matcher.pretrained("paraformer-xfeat"))
