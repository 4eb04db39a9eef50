"""Builds the README's sample pair from scikit-image's `coffee.png` (CC0, Rachel Michetti):
view 0 is the photo, view 1 the photo warped by a fixed homography H (assets/sample/H_0to1.txt).

    pip download --no-deps scikit-image && unzip -j scikit_image-*.whl 'skimage/data/coffee.png'
    python scripts/make_sample_pair.py coffee.png
"""
import sys

import cv2
import numpy as np

src = cv2.imread(sys.argv[1], cv2.IMREAD_COLOR)
if src is None:
    sys.exit(f"error: cannot read {sys.argv[1]}")
h, w = src.shape[:2]
corners = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
moved = np.float32([[40, 30], [w - 10, 55], [w - 60, h - 20], [25, h - 45]])
rot = cv2.getRotationMatrix2D((w / 2, h / 2), 12, 0.92)
H = np.vstack([rot, [0, 0, 1]]) @ cv2.getPerspectiveTransform(corners, moved).astype(np.float64)
warped = cv2.warpPerspective(src, H, (w, h), flags=cv2.INTER_LINEAR)
cv2.imwrite("assets/sample/coffee_0.jpg", src, [cv2.IMWRITE_JPEG_QUALITY, 92])
cv2.imwrite("assets/sample/coffee_1.jpg", warped, [cv2.IMWRITE_JPEG_QUALITY, 92])
np.savetxt("assets/sample/H_0to1.txt", H, fmt="%.10e")
print(H)
