"""Reference optics figures from an independent package (ray-optics) for tests/test_lens.py.

For the three prescriptions in ``tests/data/lenses/*.zmx`` (seed singlet, Cooke triplet,
double Gauss) this script lets **ray-optics** (github.com/mjhoptics/ray-optics, BSD) read the
Zemax file with its own importer and computes, in its own code:

* first-order data: EFL, BFL, FFL, principal planes, entrance/exit pupil positions and
  radii (rescaled from the file's ENPD to the stop's semi-diameter with ray-optics' own
  paraxial marginal-ray height at the stop), paraxial image distances for finite objects;
* real-ray intercepts at the paraxial image plane (infinity focus) for a grid of field
  angles × entrance-pupil coordinates, skew rays included.

Glasses: each medium ray-optics picked from its catalogue is replaced by a constant index
equal to the catalogue's measured nd (``meas_rindex('d')``), and the trace runs at 587.5618
nm, so both codes see the same indices (lfcam uses its own SCHOTT nd table / the ___BLANK
index; the JSON records the indices so a table mismatch shows up).

It writes ``tests/data/lens_reference.json`` (small). ray-optics is NOT an lfcam
dependency; use a separate virtual environment.

Regenerate (from the repository root)::

    python3 -m venv /tmp/rayenv && /tmp/rayenv/bin/pip install rayoptics   # 0.9.8 used
    /tmp/rayenv/bin/python benchmarks/lens_reference.py

The committed JSON records the ray-optics version it came from.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

# ray-optics' zmx reader opens a log file in the cwd when imported: import it (in main) from
# a scratch directory.

ROOT = Path(__file__).resolve().parents[1]
LENSES = {
    "seed_singlet": {"fields_deg": [0.0, 5.0, 10.0]},
    "cooke_triplet": {"fields_deg": [0.0, 10.0, 20.0]},
    "double_gauss": {"fields_deg": [0.0, 7.0, 14.0]},
}
WAVELENGTH_NM = 587.5618
START_GAP_MM = 20.0  # rays start on a plane this far in front of the first vertex
PUPIL = [
    (0.0, 0.0), (0.0, 1.0), (0.0, -1.0), (0.0, 0.5), (0.0, -0.5),
    (1.0, 0.0), (0.5, 0.0), (0.7, 0.7), (-0.6, 0.3), (0.35, -0.8),
]  # fmt: skip
FINITE_OBJECTS_MM = [500.0, 3500.0]


def _constant_indices(sm) -> list[float]:
    """Replace catalogue media by constant nd; return the indices after each surface."""
    from opticalglass.opticalmedium import Air, ConstantIndex

    out = []
    for gap in sm.gaps:
        med = gap.medium
        n = 1.0 if isinstance(med, Air) else float(med.meas_rindex("d"))
        if isinstance(med, ConstantIndex):
            n = float(med.rindex(WAVELENGTH_NM))
        gap.medium = Air() if n == 1.0 else ConstantIndex(n, f"n{n}")
        out.append(n)
    return out[1:]  # gap 0 is object space


def reference(name: str, fields_deg: list[float]) -> dict:
    from rayoptics.environment import open_model
    from rayoptics.raytr import raytrace

    opm = open_model(str(ROOT / "tests" / "data" / "lenses" / f"{name}.zmx"))
    sm, osp = opm["seq_model"], opm["optical_spec"]
    stop = sm.stop_surface  # read before any update_model
    if stop is None:  # ray-optics' zmx reader drops a STOP on surface 1 (too early to set)
        stop = sm.stop_surface = 1
    osp["wvls"].wavelengths = [WAVELENGTH_NM]
    indices = _constant_indices(sm)
    sm.gaps[0].thi = 1e10  # object at "infinity" as ray-optics models it
    opm.update_model()
    # ray-optics 0.9.8 measures exp_dist as if the image surface sat at the paraxial focus
    # (its value shifts by bfl − image gap otherwise): put the image surface there first.
    sm.gaps[-1].thi = opm["analysis_results"]["parax_data"].fod.bfl
    opm.update_model()
    ax_ray, _pr_ray, fod = opm["analysis_results"]["parax_data"]
    stop_sd = sm.ifcs[stop].max_aperture
    scale = stop_sd / abs(ax_ray[stop][0])  # EPD from the file → EPD of the stop's size
    n_surf = len(sm.ifcs) - 2  # lens surfaces (object and image dropped)
    vertex_z = np.concatenate([[0.0], np.cumsum([g.thi for g in sm.gaps[1:n_surf]])])
    z_last = float(vertex_z[-1])
    first = {
        "efl_mm": fod.efl,
        "bfl_mm": fod.bfl,
        "ffl_mm": fod.ffl,
        "front_principal_z_mm": fod.pp1,
        "back_principal_z_mm": z_last + fod.ppk,
        "entrance_pupil_z_mm": fod.enp_dist,
        "entrance_pupil_diameter_mm": 2.0 * fod.enp_radius * scale,
        "exit_pupil_z_mm": z_last + fod.exp_dist,
        "exit_pupil_diameter_mm": 2.0 * fod.exp_radius * scale,
        "f_number": fod.efl / (2.0 * fod.enp_radius * scale),
    }
    # real rays at infinity focus: image surface on the paraxial focal plane
    image_z = z_last + fod.bfl
    r_ep = fod.enp_radius * scale
    z_ep = fod.enp_dist
    sm.gaps[0].thi = START_GAP_MM
    sm.gaps[-1].thi = fod.bfl
    opm.update_model()
    rays = []
    for theta in fields_deg:
        d = np.array([0.0, math.sin(math.radians(theta)), math.cos(math.radians(theta))])
        for px, py in PUPIL:
            p_ep = np.array([px * r_ep, py * r_ep, z_ep])
            p0 = p_ep + d * ((-START_GAP_MM - z_ep) / d[2])
            ray, _op, _wvl = raytrace.trace(
                sm, np.array([p0[0], p0[1], 0.0]), d, WAVELENGTH_NM, last_surf=n_surf + 1
            )
            pt = ray[-1][0]  # image-surface intercept (local coords of the image surface)
            rays.append(
                {
                    "field_deg": theta,
                    "pupil": [px, py],
                    "origin_mm": [float(p0[0]), float(p0[1]), -START_GAP_MM],
                    "direction": [float(v) for v in d],
                    "image_xy_mm": [float(pt[0]), float(pt[1])],
                }
            )
    finite = []
    for dist in FINITE_OBJECTS_MM:
        sm.gaps[0].thi = dist
        opm.update_model()
        fod_f = opm["analysis_results"]["parax_data"].fod
        # image distance from the last surface of a paraxial marginal ray from the axial object
        ax = opm["analysis_results"]["parax_data"].ax_ray
        gap = -ax[n_surf][0] / ax[n_surf][1]
        finite.append({"object_distance_mm": dist, "image_gap_mm": gap, "img_dist": fod_f.img_dist})
    return {
        "indices_after_surface": indices[:n_surf],
        "stop_index": stop - 1,
        "first_order": {k: float(v) for k, v in first.items()},
        "image_plane_z_mm": float(image_z),
        "rays": rays,
        "finite_objects": finite,
    }


def main() -> None:
    os.chdir(tempfile.mkdtemp())
    import rayoptics

    out = {
        "generator": "benchmarks/lens_reference.py",
        "package": f"rayoptics {rayoptics.__version__}",
        "wavelength_nm": WAVELENGTH_NM,
        "lenses": {name: reference(name, cfg["fields_deg"]) for name, cfg in LENSES.items()},
    }
    path = ROOT / "tests" / "data" / "lens_reference.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    for name, data in out["lenses"].items():
        fo = data["first_order"]
        keys = ("efl_mm", "bfl_mm", "entrance_pupil_z_mm", "entrance_pupil_diameter_mm",
                "exit_pupil_z_mm", "exit_pupil_diameter_mm")  # fmt: skip
        print(f"{name:14s} " + " ".join(f"{k[:-3]} {fo[k]:.6f}" for k in keys))
    print(f"wrote {path.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
