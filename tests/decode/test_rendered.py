"""Decode + refocus on captures rendered by ``lfcam.sim`` (ray-traced point source and white).

The grid is the paraxial chief-ray one (micro-image pitch ``p_m·(1 + f_s/d_A)``, lens (0, 0)
on the axis), i.e. the micro-image centre definition of Hahne's model; the prediction is the
exact trace of ``test_refocus.view_positions``. A rendered view records the point in whole
lenslets, and the refocus shift interpolates bilinearly, so the measured second moment may
exceed the continuous prediction by up to 1/12 + 1/4 lenslet².
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lfcam.calibrate import Calibration
from lfcam.camera import load_profile
from lfcam.decode import decode, focal_stack, shift_for_distance, to_grey
from lfcam.sim import scene_from_dict, simulate
from tests.decode.test_refocus import _second_moment, view_positions

SIZE_PX = 384
OWN_MM = 700.0
OTHERS_MM = (300.0, 500.0, 1000.0, 1500.0, 3500.0)


@pytest.mark.parametrize("pupil_mm", [50.0, 25.0], ids=["f2", "f4"])
def test_rendered_point_source_refocus_blur(pupil_mm):
    base = load_profile("system1")
    profile = replace(base, main_lens=replace(base.main_lens, pupil_diameter_mm=pupil_mm))
    cam = {"sensor": {"width_px": SIZE_PX, "height_px": SIZE_PX},
           "main_lens": {"pupil_diameter_mm": pupil_mm}}
    white, prof, _ = simulate(base, scene_from_dict(
        {"seed": 1, "objects": [{"type": "white", "radiance": 1}], "camera": cam}))
    raw, _, truth = simulate(base, scene_from_dict(
        {"seed": 2, "rays_per_source": 1_000_000, "camera": cam,
         "objects": [{"type": "point", "distance_mm": OWN_MM, "offset_mm": 0}]}))
    assert prof.main_lens.pupil_diameter_mm == pupil_mm
    g = 1 + prof.mla.focal_length_mm / (prof.d_in_mm - prof.main_lens.exit_pupil_z_mm)
    axis = 0.5 * (SIZE_PX - 1)
    grid = Calibration.from_lattice("rect", prof.mla.pitch_mm * g / prof.sensor.pixel_pitch_mm, 0.0,
                    (axis, axis))
    lf = decode(to_grey(raw), grid, white=to_grey(white), white_threshold=0.5)
    vc, uc = lf.angular_centre
    n = lf.data.shape[0]
    vv, uu = np.meshgrid(np.arange(n) - vc, np.arange(n) - uc, indexing="ij")
    ps, pt, _ = view_positions(profile, OWN_MM, uu, vv)
    c = (-lf.first_s, -lf.first_t)  # spatial index of lens (0, 0), on the axis
    valid = (lf.weight[:, :, c[1], c[0]] > 0) & np.isfinite(ps)
    assert valid.sum() > (150 if pupil_mm == 50 else 35)
    stack = focal_stack(lf, [float(shift_for_distance(profile, d)) for d in (OWN_MM, *OTHERS_MM)])
    measured = []
    for out in stack:
        px, py = ps[valid] + out.shift * uu[valid], pt[valid] + out.shift * vv[valid]
        m = _second_moment(out.image, (c[0] + px.mean(), c[1] + py.mean()), half=8)
        for value, pred in zip(m, (px.var(), py.var()), strict=True):
            # + up to 1/12 (whole lenslets) + 1/4 (bilinear shift of a fractional a) + the
            # spread inside one view (a pixel's pupil footprint, not in the prediction; grows
            # with defocus): 0.5
            assert pred - 0.05 <= value <= pred + 0.5, (out.shift, m, pred)
        measured.append(max(m))
    if pupil_mm == 25.0:
        assert measured[0] == min(measured)  # F/4: sharpest at its own distance
        assert measured[1] > 3 * measured[0]  # 300 mm
    else:
        # F/2: spherical aberration moves the least blur away from the paraxial (Hahne) shift;
        # the metric refocus uses the trace's least-RMS shift, so the own distance is still the
        # sharpest of the set
        assert measured[0] == min(measured)
