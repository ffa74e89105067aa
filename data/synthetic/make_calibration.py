"""Reference calibrations for the full-size synthetic captures in this folder.

Run from the repository root: ``python data/synthetic/make_calibration.py`` (about 2 min).
For each shipped profile it renders a full-sensor white image and writes
``calib_<system>.json`` in lfcam's calibration format (docs/calibration.md), with the
micro-image centres set to the intensity centroids of the *traced rays* (what an error-free
white-image calibration returns), their lattice indices from the renderer, an affine lattice
model fitted to them, and ``d_in_mm`` to the profile's. ``lfcam calibrate`` output on the same
white image is compared against these in the calibration tests.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from lfcam.calibrate.model import (  # noqa: E402
    Calibration,
    calibration_from_dict,
    save_calibration,
)
from lfcam.camera import load_profile  # noqa: E402
from lfcam.sim.capture import simulate  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

SEED = 20240601


def reference_calibration(system) -> Calibration:
    """Calibration of ``system``'s full-size white image (truth centroids); ``system`` is a
    profile name or a :class:`~lfcam.camera.CameraProfile`."""
    base = load_profile(system) if isinstance(system, str) else system
    _, profile, truth = simulate(base,
                                 scene_from_dict({"seed": SEED, "objects": [{"type": "white"}]}))
    lenses = truth["lenses"]
    complete = np.asarray(lenses["complete"], dtype=bool)
    centres = np.asarray(lenses["centroid_px"], dtype=np.float64)[complete]
    mla = truth["mla"]
    basis = np.asarray(mla["basis_px"], dtype=np.float64)
    # the centroid lattice: least-squares affine fit of centroids against lattice indices
    ij = np.asarray(lenses["index_ij"], dtype=np.int64)[complete]
    a = np.column_stack([np.ones(len(ij)), ij])
    coef, *_ = np.linalg.lstsq(a, centres, rcond=None)
    resid = centres - a @ coef
    a1 = coef[1]
    matrix = np.eye(3)
    matrix[:2, 0], matrix[:2, 1], matrix[:2, 2] = coef[1], coef[2], coef[0]
    sensor = profile.sensor
    return calibration_from_dict({
        "format": "lfcam-calibration", "version": 1,
        "grid": mla["grid"],
        "pitch_px": float(np.hypot(*a1)),
        "rotation_rad": float(np.arctan2(a1[1], a1[0])),
        "offset_px": [float(coef[0, 0]), float(coef[0, 1])],
        "centres_px": np.round(centres, 5).tolist(),
        "indices": ij.tolist(),
        "model": "affine",
        "lattice_matrix": matrix.tolist(),
        "image_size_px": [sensor.width_px, sensor.height_px],
        "residual_rms_px": float(np.sqrt((resid**2).sum(axis=1).mean())),
        "d_in_mm": float(profile.d_in_mm),
        "d_in_method": "profile",
        "centre_definition": "intensity centroid of the white image (ray-traced truth)",
        "diagnostics": {"white_image": f"lfcam.sim white scene, seed {SEED}",
                        "profile": profile.name, "lattice_basis_px": basis.tolist()},
    })


def main() -> None:
    """Write calib_<profile>.json for the seed systems and the two multi-element lenses
    (``python data/synthetic/make_calibration.py [PROFILE ...]`` for a subset)."""
    systems = sys.argv[1:] or ["system1", "system2", "cooke_triplet", "double_gauss"]
    for system in systems:
        path = HERE / f"calib_{system}.json"
        save_calibration(reference_calibration(system), path)
        print(f"wrote {path.name}")


if __name__ == "__main__":
    main()
