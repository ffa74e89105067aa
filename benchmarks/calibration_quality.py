"""Calibration quality figures on good and bad white images (docs/robustness.md, issue 18).

Run from the repository root: ``python benchmarks/calibration_quality.py`` (~1 min). Prints,
per white image, the quantities the quality gates of :mod:`lfcam.calibrate.quality` read:
coverage (lenses measured / fully visible lattice sites found), lattice residual RMS (px and
fraction of the pitch), disc-model misfit, and the verdict.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.calibrate import calibrate_white, calibrate_white_file  # noqa: E402
from lfcam.calibrate.quality import assess  # noqa: E402
from lfcam.io import load_capture  # noqa: E402

REAL = Path("/work/shared/realdata/microscope")
BAD_SCENE = {"seed": 3, "samples_per_pixel": 1, "objects": [{"type": "white"}],
             "camera": {"sensor": {"width_px": 1288, "height_px": 1288}}}


def bad_white(folder: Path) -> Path:
    """A system 2 white rendered with one sample per boundary pixel (heavy Monte-Carlo noise)."""
    from lfcam.camera import load_profile
    from lfcam.sim.capture import simulate, write_capture
    from lfcam.sim.scene import scene_from_dict

    raw, used, truth = simulate(load_profile("system2"), scene_from_dict(BAD_SCENE))
    img, _, _ = write_capture(folder / "bad_white_system2.png", raw, used, truth)
    return img


def main() -> None:
    cases = []
    for name in ("system1_rect", "system1_hex", "system2_rect", "system2_hex"):
        cases.append((f"data/synthetic {name}",
                      lambda n=name: calibrate_white_file(ROOT / f"data/synthetic/white_{n}.png")))
    for folder, white, dark in (("guv", "Radiometry_GUVExperim1.tif",
                                 "DarkFrame_GUVExperim1.tif"),
                                ("seaurchin", "radiometry_frame.tif", "dark_frame.tif")):
        if (REAL / folder).is_dir():
            def real(f=folder, w=white, d=dark):
                a = np.asarray(load_capture(REAL / f / w).raw, np.float32)
                b = np.asarray(load_capture(REAL / f / d).raw, np.float32)
                return calibrate_white(a, b)
            cases.append((f"microscope {folder}", real))
    tmp = Path(tempfile.mkdtemp(prefix="lfcam-calq-"))
    cases.append(("system2 1288², 1 sample/px (bad)",
                  lambda: calibrate_white_file(bad_white(tmp))))
    print(f"{'white':36s} {'lenses':>6s} {'expect':>6s} {'cover':>6s} {'rms px':>7s} "
          f"{'rms/p':>7s} {'misfit':>7s} {'method':>18s}  verdict")
    for name, fn in cases:
        cal = fn()
        q = assess(cal)
        print(f"{name:36s} {cal.n_lenses:6d} {q.expected:6d} {q.coverage:6.3f} "
              f"{q.residual_rms_px:7.4f} {q.residual_rel_pitch:7.4f} "
              f"{q.misfit if q.misfit is not None else float('nan'):7.4f} "
              f"{str(cal.diagnostics.get('centroid_method')):>18s}  {q.verdict} "
              f"{'; '.join(q.reasons)}")


if __name__ == "__main__":
    main()
