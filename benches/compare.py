"""Side-by-side speed comparison, in one run, on the same weights and thread count:
the PyTorch reference model (training/paraformer_train) against the Rust engine
(the installed `paraformer` module), plus numpy's float32 GEMM rate.

    pip install . torch safetensors          # the module, and the reference's needs
    python benches/compare.py                # 2 threads, 2048 keypoints, all models
    python benches/compare.py --keypoints 512 1024 2048 --threads 2 --json benches/results.json
    python benches/compare.py --shipped --threads 2    # shipped matchers vs LighterGlue, fp32/bf16

Prints, per model: PyTorch and Rust latency and their ratio, the Rust network part's
FLOP rate (2·MACs / time, everything but Sinkhorn) against numpy's GEMM rate, the
Sinkhorn share of end-to-end time, ParaFormer-U's latency relative to ParaFormer, and
the bf16 row: Rust with `precision="bf16"` (where the CPU has AVX-512 BF16), its speed-up
over Rust fp32 and the share of its matches equal to fp32's. The shipped models against
LighterGlue on real pairs: `benches/shipped_compare.py`.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--keypoints", type=int, nargs="+", default=[2048])
    ap.add_argument("--models", nargs="+", default=["superglue", "paraformer", "paraformer_u"])
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per case (the best is kept)")
    ap.add_argument("--json", help="also write the results to this file")
    ap.add_argument("--shipped", action="store_true",
                    help="instead: the shipped matchers (fp32, bf16) against LighterGlue on real pairs "
                         "(runs benches/shipped_compare.py with --threads and --json)")
    args = ap.parse_args()
    if args.shipped:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import shipped_compare

        sys.argv = [sys.argv[0], "--threads", str(args.threads)] + (["--json", args.json] if args.json else [])
        shipped_compare.main()
        return
    # Thread counts must be fixed before the libraries start their pools.
    for var in ("RAYON_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import numpy as np
    import torch
    import paraformer

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "training"))
    from paraformer_train import Matcher as TorchMatcher, save_safetensors

    torch.set_num_threads(args.threads)

    def best(fn, repeat):
        fn()  # warm-up
        times = []
        for _ in range(repeat):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times)

    # numpy float32 GEMM rate, the reference for the engine's FLOP rate.
    a = np.random.default_rng(0).standard_normal((2048, 2048), dtype=np.float32)
    gemm_s = best(lambda: a @ a, 5)
    numpy_gflops = 2 * 2048**3 / gemm_s / 1e9
    print(f"threads {args.threads}; numpy sgemm 2048³: {numpy_gflops:.1f} GFLOP/s; torch {torch.__version__}")

    rng = np.random.default_rng(1)
    results = []
    header = (f"{'model':<13}{'kp':>6}{'torch s':>10}{'rust s':>9}{'speed-up':>10}"
              f"{'net GFLOP/s':>13}{'/ numpy':>9}{'sinkhorn':>10}{'matches =':>11}"
              f"{'bf16 s':>9}{'bf16/fp32':>10}{'bf16 =':>8}")
    print(header)
    rust_models = {}
    with tempfile.TemporaryDirectory() as tmp:
        for model_name in args.models:
            torch.manual_seed(0)
            ref = TorchMatcher({"model": model_name}).eval()
            with torch.no_grad():  # non-trivial norm statistics, as trained weights have
                for name, buf in ref.named_buffers():
                    if name.endswith("running_var"):
                        buf.uniform_(0.5, 1.5)
            path = os.path.join(tmp, f"{model_name}.safetensors")
            save_safetensors(ref, path)
            rust = paraformer.Matcher.from_file(path)
            rust16 = paraformer.Matcher.from_file(path, precision="bf16")
            for k in args.keypoints:
                kp = [rng.uniform(0, 640, (k, 2)).astype(np.float32) for _ in range(2)]
                desc = [rng.standard_normal((k, 256)).astype(np.float32) for _ in range(2)]
                sc = [rng.uniform(0, 1, k).astype(np.float32) for _ in range(2)]
                size = (640.0, 480.0)
                data = {f"keypoints{i}": torch.from_numpy(kp[i])[None] for i in range(2)}
                data.update({f"descriptors{i}": torch.from_numpy(desc[i])[None] for i in range(2)})
                data.update({f"scores{i}": torch.from_numpy(sc[i])[None] for i in range(2)})
                data.update({f"image_size{i}": torch.tensor([size]) for i in range(2)})

                def run_torch():
                    with torch.no_grad():
                        return ref(data)

                def run_rust():
                    return rust.match(kp[0], desc[0], kp[1], desc[1], size0=size, size1=size, scores0=sc[0], scores1=sc[1])

                def run_bf16():
                    return rust16.match(kp[0], desc[0], kp[1], desc[1], size0=size, size1=size, scores0=sc[0], scores1=sc[1])

                t_torch = best(run_torch, args.repeat)
                # fp32 and bf16 alternated call by call, the best of each kept.
                run_rust(), run_bf16()
                t32, t16 = [], []
                for _ in range(max(3, args.repeat)):
                    for fn, ts in ((run_rust, t32), (run_bf16, t16)):
                        t = time.perf_counter()
                        fn()
                        ts.append(time.perf_counter() - t)
                t_rust, t_bf16 = min(t32), min(t16)
                same16 = float((run_bf16()["matches0"] == run_rust()["matches0"]).mean())
                prof = min((rust.profile(kp[0], desc[0], kp[1], desc[1], size0=size, size1=size,
                                         scores0=sc[0], scores1=sc[1]) for _ in range(args.repeat)),
                           key=lambda p: p["total"])
                net_s = prof["encoder"] + prof["layers"] + prof["final_projection"]
                net_gflops = 2 * prof["macs"] / net_s / 1e9
                same = float((run_torch()["matches0"][0].numpy() == run_rust()["matches0"]).mean())
                row = {
                    "model": model_name, "keypoints": k, "threads": args.threads,
                    "torch_s": t_torch, "rust_s": t_rust, "speedup": t_torch / t_rust,
                    "rust_profile": prof, "net_gflops": net_gflops, "numpy_gflops": numpy_gflops,
                    "net_fraction_of_numpy": net_gflops / numpy_gflops,
                    "sinkhorn_fraction": prof["sinkhorn"] / prof["total"], "matches_agree": same,
                    "bf16_runs_as": rust16.precision, "rust_bf16_s": t_bf16, "bf16_speedup_over_fp32": t_rust / t_bf16,
                    "bf16_matches_agree_with_fp32": same16,
                }
                results.append(row)
                print(f"{model_name:<13}{k:>6}{t_torch:>10.3f}{t_rust:>9.3f}{row['speedup']:>9.1f}×"
                      f"{net_gflops:>13.1f}{row['net_fraction_of_numpy']:>8.0%} {row['sinkhorn_fraction']:>9.1%}"
                      f"{same:>10.1%}{t_bf16:>9.3f}{t_rust / t_bf16:>9.2f}×{same16:>8.1%}")
            rust_models[model_name] = (rust, path)
    # ParaFormer-U against ParaFormer: the two Rust engines alternated call by call, so
    # that both see the same machine state; the best of each is compared.
    ratios = {}
    if {"paraformer", "paraformer_u"} <= set(rust_models):
        p, u = rust_models["paraformer"][0], rust_models["paraformer_u"][0]
        for k in args.keypoints:
            kp = [rng.uniform(0, 640, (k, 2)).astype(np.float32) for _ in range(2)]
            desc = [rng.standard_normal((k, 256)).astype(np.float32) for _ in range(2)]
            run = lambda m: m.match(kp[0], desc[0], kp[1], desc[1], size0=(640, 480), size1=(640, 480))  # noqa: E731
            run(p), run(u)
            tp, tu = [], []
            for _ in range(max(5, args.repeat)):
                for m, ts in ((p, tp), (u, tu)):
                    t = time.perf_counter()
                    run(m)
                    ts.append(time.perf_counter() - t)
            ratios[k] = min(tu) / min(tp)
            print(f"ParaFormer-U / ParaFormer latency at {k} keypoints (Rust, alternated): "
                  f"{min(tu):.3f} / {min(tp):.3f} s = {ratios[k]:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"numpy_gflops": numpy_gflops, "results": results,
                                               "u_over_p_latency": ratios}, indent=1) + "\n")


if __name__ == "__main__":
    main()
