"""Run PlenoptiCam's white-image calibration on one image; called by benchmarks/calibrate.py.

This file runs under a *foreign* interpreter (a throwaway venv with ``plenopticam``
installed), so it imports nothing from lfcam and only numpy + plenopticam.

Usage:  <venv>/bin/python plenopticam_driver.py IMAGE.npy OUT.npz [METHOD [M]]

IMAGE.npy is a 2-D monochrome white image (rows × columns). METHOD is one of PlenoptiCam's
``cal_meth`` values (default ``area``, the tool's own default). M is the micro-image size
in pixels handed to ``LfpCalibrator`` instead of its own estimate (``auto``, the default,
keeps the estimate; ``LfpCalibrator.main`` uses a preset ``_M`` when one is set). OUT.npz receives
``centres_xy`` (final, sorted micro-image centres as x = column, y = row, pixel centres at
integers — the same convention as lfcam), ``refined_xy`` (the refined detections before
sorting), ``stage_names`` / ``stage_s`` (seconds per stage, from the tool's own status
messages) and ``total_s`` (wall time of ``LfpCalibrator.main()`` alone, image already in
memory).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np


def main() -> None:
    """Load the image, run ``LfpCalibrator.main()``, save centres and timings."""
    image_path, out_path = sys.argv[1], sys.argv[2]
    method = sys.argv[3] if len(sys.argv) > 3 else "area"
    m_px = sys.argv[4] if len(sys.argv) > 4 else "auto"

    import plenopticam
    from plenopticam.cfg import PlenopticamConfig
    from plenopticam.lfp_calibrator import top_level
    from plenopticam.misc.status import PlenopticamStatus

    marks: list[tuple[str, float]] = []

    class TimedStatus(PlenopticamStatus):
        """Status object that timestamps every stage message (no effect on the computation)."""

        def status_msg(self, msg="", opt=False):
            marks.append((str(msg), time.perf_counter()))
            print(f"\n[plenopticam {time.strftime('%H:%M:%S')}] {msg}", flush=True)
            return super().status_msg(msg, opt=False)

        def progress(self, x, opt=False):
            return super().progress(x, opt=False)

    refined: list[np.ndarray] = []
    sorter_cls = top_level.CentroidSorter

    class RecordingSorter(sorter_cls):
        """Keeps a copy of the refined detections handed to the sorter."""

        def __init__(self, centroids, *args, **kwargs):
            refined.append(np.asarray(centroids, dtype=np.float64).copy())
            super().__init__(centroids, *args, **kwargs)

    top_level.CentroidSorter = RecordingSorter

    img = np.load(image_path).astype(np.float64)
    img /= img.max()
    tmp = Path(out_path).resolve().parent  # the caller's temporary folder
    cfg = PlenopticamConfig()
    cfg.params[cfg.cal_meth] = method
    cfg.params[cfg.opt_dbug] = False
    cfg.params[cfg.opt_prnt] = False
    cfg.params[cfg.cal_meta] = str(tmp / "calib.json")
    sta = TimedStatus()
    print(f"[plenopticam] version {getattr(plenopticam, '__version__', '?')}, method {method}, "
          f"M {m_px}, image {img.shape[1]}x{img.shape[0]}", flush=True)
    t0 = time.perf_counter()
    cal = top_level.LfpCalibrator(img, cfg, sta)
    if m_px != "auto":
        cal._M = int(m_px)
    cal.main()
    t1 = time.perf_counter()
    mics = np.asarray(cfg.calibs.get(cfg.mic_list, []), dtype=np.float64).reshape(-1, 4)
    names = [m for m, _ in marks]
    bounds = [t0] + [t for _, t in marks[1:]] + [t1]
    stage_s = np.diff(np.array(bounds)) if marks else np.zeros(0)
    ref = refined[0] if refined else np.zeros((0, 2))
    np.savez(out_path, centres_xy=mics[:, [1, 0]] if len(mics) else np.zeros((0, 2)),
             refined_xy=ref[:, [1, 0]] if len(ref) else np.zeros((0, 2)),
             stage_names=np.array(names), stage_s=stage_s, total_s=t1 - t0,
             tool_error=bool(sta.error), m_used=int(cal._M or 0),
             version=str(getattr(plenopticam, "__version__", "?")))
    print(f"[plenopticam] done in {t1 - t0:.1f} s, {len(mics)} centres", flush=True)


if __name__ == "__main__":
    main()
