"""Benchmark: where decode puts the lenses, before and after it used the fitted lattice model.

Decode needs a centre for every lens on the sensor. Measured lenses keep their measured
centre; for every other lens (rejected as ``edge``/``dim``/``outlier``, or never detected)
decode used to take the plain rotation-and-pitch (similarity) lattice of the calibration file,
ignoring the affine / projective / radial model that calibration fitted. It now takes
:meth:`lfcam.calibrate.Calibration.predict`.

The figure: hold every measured lens out in turn and compare where each placement rule puts
it with where it was measured (RMS and max over the frame, px), on real light-field
microscope frames whose lattice needs the radial term (``../shared/realdata/microscope``).

Run:  python benchmarks/decode_lattice.py      (~30 s)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.calibrate import Calibration, calibrate_white  # noqa: E402
from lfcam.io import load_capture  # noqa: E402

REAL = ROOT.parent / "shared" / "realdata" / "microscope"
FRAMES = (("seaurchin", "radiometry_frame.tif", "dark_frame.tif"),
          ("guv", "Radiometry_GUVExperim1.tif", "DarkFrame_GUVExperim1.tif"))


def placement_errors(cal: Calibration) -> dict[str, tuple[float, float]]:
    """(RMS, max) px of each placement rule at the measured lenses."""
    plain = Calibration.from_lattice(cal.grid, cal.pitch_px, cal.rotation_rad, cal.offset_px)
    out = {}
    for name, pred in (("similarity (before)", plain.predict(cal.indices)),
                       (f"{cal.model} (after)", cal.predict(cal.indices))):
        r = np.hypot(*(cal.centres_px - pred).T)
        out[name] = (float(np.sqrt(np.mean(r * r))), float(r.max()))
    return out


def main() -> None:
    """Calibrate each frame and print the table."""
    if not REAL.is_dir():
        print(f"real data not found at {REAL}: nothing to measure")
        return
    print(f"{'frame':10} {'lenses':>7} {'placement of unmeasured lenses':32} "
          f"{'RMS px':>8} {'max px':>8}")
    for folder, white, dark in FRAMES:
        t0 = time.perf_counter()
        w = np.asarray(load_capture(REAL / folder / white).raw, np.float32)
        d = np.asarray(load_capture(REAL / folder / dark).raw, np.float32)
        cal = calibrate_white(w, d)
        for rule, (rms, mx) in placement_errors(cal).items():
            print(f"{folder:10} {cal.n_lenses:7d} {rule:32} {rms:8.3f} {mx:8.3f}")
        # decode's grid: measured lenses exactly where measured
        lc = cal.lens_centres(w.shape)
        placed = np.column_stack([lc.x.ravel(), lc.y.ravel()])
        dist = np.min(np.hypot(*(placed[:, None, :] - cal.centres_px[None, :200, :]).transpose(
            2, 0, 1)), axis=0)
        print(f"{'':10} decode keeps measured centres: max |Δ| = {dist.max():.2e} px "
              f"(first 200); {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
