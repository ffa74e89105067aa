"""A ray's share across a lenslet cell's border (``lfcam.measure.sampling.ray_share``).

The lenslet model shares each ray of its pupil sample between the two cells it lies between,
so that its moments stay continuous in the source position. One box of the ray spacing g
shares light as a convolution with that box would, and adds the box's variance g²/12 to
every footprint; the two boxes' combination has none (docs/distance.md, "Ray shares without
the box's variance (stop 53)").
"""

from __future__ import annotations

import numpy as np
import pytest

from lfcam.camera import load_profile
from lfcam.measure import fastfit as ff
from lfcam.measure.pointfit import chief_ray_offset
from lfcam.measure.sampling import ray_share
from lfcam.sim.capture import apply_overrides
from lfcam.sim.geometry import truth_geometry

SIZE = 1024


@pytest.mark.parametrize(("richardson", "variance"), [(False, 1.0 / 12.0), (True, 0.0)])
def test_share_rule_is_a_kernel_of_the_stated_moments(richardson, variance):
    # A cell border at u = 0: a ray at u belongs to the cell u > 0 by 1 − share(|u|) on its
    # side and by share(|u|) on the other. That membership is the cell's indicator convolved
    # with a kernel (its derivative): of unit mass, no first moment, and a second moment of
    # g²/12 for the box, 0 for the combination (analytic values)
    g = 0.37
    u = np.linspace(-3 * g, 3 * g, 600_001)
    share = ray_share(np.abs(u), g, richardson)
    member = np.where(u > 0, 1.0 - share, share)
    kernel = np.gradient(member, u)
    du = u[1] - u[0]
    assert np.sum(kernel) * du == pytest.approx(1.0, abs=1e-6)
    assert np.sum(u * kernel) * du == pytest.approx(0.0, abs=1e-7)
    assert np.sum(u * u * kernel) * du == pytest.approx(variance * g * g, abs=1e-6 * g * g)
    # the combination gives light back beyond half a spacing, and nothing beyond one
    if richardson:
        assert ray_share(np.array([0.75 * g]), g)[0] < 0.0
        assert ray_share(np.array([1.0 * g]), g)[0] == 0.0


def _system1():
    prof = apply_overrides(load_profile("system1"), {"mla": {"focus_mm": 1000.0},
                                                     "sensor": {"width_px": SIZE,
                                                                "height_px": SIZE}})
    prof = prof.with_d_in(prof.d_in_mm)
    return prof, truth_geometry(prof, (SIZE, SIZE))


def _source(prof, distance_mm, field):
    """A point whose chief ray meets the MLA at ``field`` of the sensor's half-width."""
    half = 0.5 * SIZE * prof.sensor.pixel_pitch_mm
    mla = field * half * prof.d_in_mm / (prof.d_in_mm + prof.mla.focal_length_mm)
    xy = chief_ray_offset(prof, prof.d_in_mm, distance_mm, np.array([mla, 0.0]))
    return np.array([[xy[0], xy[1], prof.main_lens.front_vertex_z_mm - distance_mm]])


@pytest.mark.parametrize(("distance_mm", "field", "box"), [
    (3400.0, 0.0, (425, 425, 597, 597)), (2200.0, 0.6, (753, 409, 973, 613))])
def test_ray_shares_leave_a_small_blur_far_behind_focus_its_distance(monkeypatch, distance_mm,
                                                                     field, box):
    # System 1 behind a 1 m focus, where a blur grows by ~0.3 % for 1 % of distance: the
    # lenslets' light of a 2 500-ray sample (8 turns averaged) against a 400 000-ray one,
    # read as the distance the dense model would need to give that light (least squares on
    # its distance derivative). With one box the sample reads 0.3 % far (measured 3.3e-3
    # and 2.9e-3); with the combination under a third of that (4.7e-4, 8.2e-4)
    prof, geom = _system1()
    mom = ff.data_moments(geom, np.zeros((SIZE, SIZE)), box)

    def light(model, d):
        m0 = model.simulate(_source(prof, d, field))[:, 0]
        return m0 / m0.sum()

    dense = ff.LensletModel(prof, geom, mom, 400_000)
    ref = light(dense, distance_mm)
    slope = (light(dense, 1.01 * distance_mm) - light(dense, 0.99 * distance_mm)) / 0.02

    def shift(richardson: bool) -> float:
        monkeypatch.setattr(ff, "RAY_SHARE_RICHARDSON", richardson)
        sample = np.mean([light(ff.LensletModel(prof, geom, mom, 2500, phase=0.7 * k),
                                distance_mm) for k in range(8)], axis=0)
        return float(slope @ (sample - ref)) / float(slope @ slope)

    box_shift, share_shift = shift(False), shift(True)
    assert box_shift > 2e-3
    assert abs(share_shift) < box_shift / 3.0
