"""Benchmark: white-image calibration against the renderer's ray-traced centroids.

Cases: the committed ``data/synthetic`` white crops (both systems, rect and hex, unrotated),
the rotated / offset / noisy crops of ``tests/test_calibrate_rendered.py``, and full-sensor
whites of both shipped profiles (system 1 1024², system 2 1536²). Truth: ``lenses.centroid_px``
of each render (intensity centroid of the light of that lenslet, from the traced rays);
pitch and rotation truth: a similarity fit of those centroids on their lenslet indices.

Columns: centroid method chosen, lenses accepted / fully visible (renderer's ``complete``),
missed, invented (accepted centres farther than pitch/4 from every lit lenslet), centre RMS and
max error (px) over the fully visible lenses, pitch relative error, rotation error (rad),
calibration time (s; render time excluded).

Run:  python benchmarks/calibrate_rendered.py   (~1 min on 2 cores)
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.calibrate import calibrate_white  # noqa: E402
from lfcam.calibrate.grid import fit_similarity  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.io import load_capture  # noqa: E402
from lfcam.sim.capture import simulate  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

NOISE = {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 5.0}
RENDERED = [
    # label, system, grid, rotation °, MLA offset (mm), noisy, sensor px (None: full sensor)
    ("s1 rect 1.7° off", "system1", "rect", 1.7, (0.31, -0.17), False, 320),
    ("s1 hex -1.9° off", "system1", "hex", -1.9, (-0.21, 0.43), False, 320),
    ("s2 rect 2.0° off", "system2", "rect", 2.0, (0.061, 0.023), False, 320),
    ("s2 hex -1.3° off", "system2", "hex", -1.3, (0.037, -0.052), False, 320),
    ("s1 hex 0.8° noisy", "system1", "hex", 0.8, (0.11, 0.05), True, 320),
    ("s2 rect -1.6° noisy", "system2", "rect", -1.6, (-0.044, 0.018), True, 320),
    ("s1 rect full 1024²", "system1", "rect", 0.0, (0.0, 0.0), True, None),
    ("s2 rect full 1536²", "system2", "rect", 0.0, (0.0, 0.0), True, None),
]


def render(system, grid, rot_deg, offset_mm, noisy, size):
    """Render one white image; returns (raster, truth)."""
    camera = {"mla": {"grid": grid, "rotation_rad": float(np.deg2rad(rot_deg)),
                      "offset_mm": list(offset_mm)}}
    if size is not None:
        camera["sensor"] = {"width_px": size, "height_px": size}
    scene = {"seed": 11, "objects": [{"type": "white"}], "camera": camera}
    if noisy:
        scene["sensor"] = NOISE
    raw, _, truth = simulate(load_profile(system), scene_from_dict(scene))
    return raw.astype(np.float32), truth


def score(image, truth):
    """Calibrate and compare with the truth; returns a table row (list of str)."""
    t0 = time.perf_counter()
    cal = calibrate_white(image)
    dt = time.perf_counter() - t0
    lenses = truth["lenses"]
    tc = np.asarray(lenses["centroid_px"], dtype=np.float64)
    complete = np.asarray(lenses["complete"]).astype(bool)
    ij = np.asarray(lenses["index_ij"], dtype=np.int64)
    d, k = cKDTree(tc).query(cal.centres_px)
    invented = int(np.sum(d > 0.25 * cal.pitch_px))
    found = np.zeros(len(tc), bool)
    found[k[d <= 0.25 * cal.pitch_px]] = True
    sel = complete[k] & (d <= 0.25 * cal.pitch_px)
    err = np.hypot(*(cal.centres_px[sel] - tc[k[sel]]).T)
    grid = truth["mla"]["grid"]
    _, pitch_t, rot_t, _ = fit_similarity(ij[complete], tc[complete], grid)
    period = np.pi / 2 if grid == "rect" else np.pi / 3
    drot = (cal.rotation_rad - rot_t + period / 2) % period - period / 2
    return [cal.diagnostics.get("centroid_method", "?"),
            f"{len(cal.centres_px)}/{int(complete.sum())}",
            str(int(np.sum(complete & ~found))), str(invented),
            f"{np.sqrt(np.mean(err**2)):.4f}", f"{err.max():.4f}",
            f"{abs(cal.pitch_px - pitch_t) / pitch_t:.1e}", f"{abs(drot):.1e}", f"{dt:.2f}"]


def main() -> None:
    """Print the table."""
    head = ["case", "method", "lenses", "missed", "invented", "rms px", "max px", "pitch rel",
            "rot rad", "time s"]
    rows = []
    for name in ("white_system1_rect", "white_system1_hex", "white_system2_rect",
                 "white_system2_hex"):
        base = ROOT / "data" / "synthetic" / name
        truth = json.loads(base.with_suffix(".truth.json").read_text(encoding="utf-8"))
        white = load_capture(base.with_suffix(".png")).raw
        rows.append([name.removeprefix("white_")] + score(white, truth))
        print(" | ".join(rows[-1]), flush=True)
    for label, *case in RENDERED:
        image, truth = render(*case)
        rows.append([label] + score(image, truth))
        print(" | ".join(rows[-1]), flush=True)
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]
    print()
    print("  ".join(h.ljust(w) for h, w in zip(head, widths, strict=True)))
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)))


if __name__ == "__main__":
    main()
