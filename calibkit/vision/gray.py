"""One image to one channel: the gray conversion every capture and board finder shares.

Cameras deliver grayscale, BGR or BGRA frames; dot captures, board finders and settle
detection all want one channel. One function, one formula (OpenCV's BGR weights
0.114 B + 0.587 G + 0.299 R), so the same frame gives the same gray everywhere.
"""

from __future__ import annotations

import cv2
import numpy as np

_CV_DEPTHS = (np.uint8, np.uint16, np.float32)


def to_gray(image: np.ndarray, dtype=None) -> np.ndarray:
    """A (H, W) image from a (H, W), (H, W, 1), BGR or BGRA one.

    dtype: convert to it before the weighting (np.float32 keeps the weighted sum's
    fraction instead of rounding it to the input's integers, which centroids want);
    None keeps the input's type (uint8 for OpenCV's board finders)."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if dtype is not None:
        img = img.astype(dtype, copy=False)
    if img.ndim == 2:
        return img
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ValueError(f"expected a grayscale, BGR or BGRA image, got shape {img.shape}")
    work = img if img.dtype in _CV_DEPTHS else img.astype(np.float32)
    gray = cv2.cvtColor(np.ascontiguousarray(work[:, :, :3]), cv2.COLOR_BGR2GRAY)
    return gray if dtype is None or gray.dtype == dtype else gray.astype(dtype)
