"""FLOPs (multiply-accumulates, SPEC §10) against keypoints for SuperGlue, ParaFormer and
ParaFormer-U at the paper's widths: the curves of the paper's Figure 7 and the column of
its Table 7, from ``paraformer.flops``.

    pip install . matplotlib
    python benches/flops_plot.py                     # writes benches/results/flops.png
"""
from __future__ import annotations

import argparse
from pathlib import Path

import paraformer

MODELS = [("superglue", "SuperGlue"), ("paraformer", "ParaFormer"), ("paraformer_u", "ParaFormer-U")]
PAPER_2048 = {"superglue": 125.85, "paraformer": 104.22, "paraformer_u": 61.67}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "flops.png"))
    args = ap.parse_args()
    ks = list(range(128, 4097, 128))
    curves = {m: [paraformer.flops({"model": m}, k, k) / 1e9 for k in ks] for m, _ in MODELS}
    print(f"{'keypoints':>10}" + "".join(f"{label:>15}" for _, label in MODELS))
    for k in (512, 1024, 2048):
        print(f"{k:>10}" + "".join(f"{paraformer.flops({'model': m}, k, k) / 1e9:>15.2f}" for m, _ in MODELS))
    print(f"{'paper 2048':>10}" + "".join(f"{PAPER_2048[m]:>15.2f}" for m, _ in MODELS))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    for m, label in MODELS:
        ax.plot(ks, curves[m], label=label, linewidth=2)
        ax.scatter([2048], [PAPER_2048[m]], marker="x", color="black", zorder=3)
    ax.scatter([], [], marker="x", color="black", label="paper, Table 7")
    ax.set_xlabel("keypoints per image")
    ax.set_ylabel("GMACs (paper: FLOPs (G))")
    ax.set_title("Matcher cost against keypoints (SPEC §10)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
