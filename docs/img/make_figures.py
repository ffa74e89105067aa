"""Small preview PNGs for docs/simulate.md from data/synthetic (run data/synthetic/make.py first).

Run from the repository root: ``python docs/img/make_figures.py``.
"""

from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "data" / "synthetic"
OUT = Path(__file__).resolve().parent


def save(name: str, raw: np.ndarray, gamma: float = 0.5) -> None:
    v = (raw.astype(np.float64) / max(int(raw.max()), 1)) ** gamma
    cv2.imwrite(str(OUT / name), np.rint(255 * v).astype(np.uint8))


def crop(raw, cx, cy, half):
    return raw[cy - half:cy + half, cx - half:cx + half]


white = cv2.imread(str(DATA / "white_system2_hex.png"), cv2.IMREAD_UNCHANGED)
save("white_system2_hex_crop.png", crop(white, 384, 384, 96), 1.0)
white1 = cv2.imread(str(DATA / "white_system1_rect.png"), cv2.IMREAD_UNCHANGED)
save("white_system1_rect_crop.png", crop(white1, 256, 256, 96), 1.0)
point = cv2.imread(str(DATA / "point_system1_300mm_dh10.png"), cv2.IMREAD_UNCHANGED)
save("point_system1_300mm_dh10.png", crop(point, 512, 512 + 0, 128))
line = cv2.imread(str(DATA / "line_system1_600mm.png"), cv2.IMREAD_UNCHANGED)
save("line_system1_600mm.png", crop(line, 512, 490, 96))
