"""SIFT features (OpenCV) for every image of a folder, written as a paraformer features file.

    pip install . opencv-python-headless
    python scripts/extract_sift.py IMAGE_DIR features.safetensors --max-keypoints 1024

Image names in the file are paths relative to IMAGE_DIR (as the datasets name them).
Descriptors are RootSIFT-free plain SIFT, L2-normalised; scores are the detector responses.
"""
import argparse
from pathlib import Path

import cv2
import numpy as np

import paraformer


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("images")
    ap.add_argument("out")
    ap.add_argument("--max-keypoints", type=int, default=1024)
    args = ap.parse_args()
    root = Path(args.images)
    files = sorted(p for p in root.iterdir() if p.suffix.lower() in {".jpg", ".jpeg", ".png", ".pgm", ".ppm"})
    sift = cv2.SIFT_create(nfeatures=args.max_keypoints)
    feats = {}
    for i, p in enumerate(files):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        kps, desc = sift.detectAndCompute(img, None)
        kps, desc = kps[: args.max_keypoints], (desc if desc is not None else np.zeros((0, 128), np.float32))[: args.max_keypoints]
        desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        feats[p.name] = {"keypoints": np.array([k.pt for k in kps], np.float32).reshape(-1, 2),
                         "scores": np.array([k.response for k in kps], np.float32),
                         "descriptors": desc.astype(np.float32), "image_size": (img.shape[1], img.shape[0])}
        print(f"\r{i + 1}/{len(files)} {p.name}: {len(kps)} keypoints", end="", flush=True)
    print()
    paraformer.features.write(args.out, feats)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
