"""Property-based checks over the whole domain, extremes included (hypothesis)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lfcam import load_profile
from lfcam.models import POINT_MODELS, exact, line
from lfcam.models.base import Status
from lfcam.optics.trace import forward

PROFILES = {name: load_profile(name) for name in ("system1", "system2")}
FOCI = st.one_of(st.just(math.inf), st.floats(300.0, 1e5))


@st.composite
def case(draw):
    """(profile, distance, offset): extremes drawn on purpose."""
    base = PROFILES[draw(st.sampled_from(sorted(PROFILES)))]
    focus = draw(FOCI)
    p = base.with_focus(focus)
    f = p.main_lens.focal_length_mm
    half = 0.5 * p.main_lens.pupil_diameter_mm
    kind = draw(st.sampled_from(["any", "focused", "near-f", "far"]))
    if kind == "focused":
        dist = focus if math.isfinite(focus) else 1e6
    elif kind == "near-f":
        dist = draw(st.floats(0.99 * f, 1.01 * f))
    elif kind == "far":
        dist = draw(st.floats(1e5, 1e6))
    else:
        dist = draw(st.floats(1.2 * f, 1e6))
    edge = draw(st.booleans())
    off = draw(st.floats(-0.9999, 0.9999)) * half if edge else draw(st.floats(-0.9, 0.9)) * half
    as32 = draw(st.booleans())
    if as32:
        dist, off = float(np.float32(dist)), float(np.float32(off))
    return p, dist, off, as32


@settings(max_examples=300, deadline=None)
@given(case())
def test_forward_then_exact_inverse_round_trips(c):
    p, dist, off, as32 = c
    dtype = np.float32 if as32 else np.float64
    fw = forward(p, None, np.array([dist], dtype=dtype), np.array([off], dtype=dtype))
    if fw.status[0] != 0:
        assert np.isnan(fw.y1_mm[0]) and np.isnan(fw.y2_mm[0])
        return
    inv = exact.invert(p, None, fw.y1_mm, fw.y2_mm)
    f = p.main_lens.focal_length_mm
    if dist >= 1.2 * f and abs(off) <= 0.45 * p.main_lens.pupil_diameter_mm:
        assert inv.status[0] == Status.OK
    if inv.status[0] == Status.OK:
        assert abs(inv.distance_mm[0] - dist) <= 1e-9 * dist
        assert abs(inv.offset_mm[0] - off) <= 1e-9 * dist
    else:
        assert np.isnan(inv.distance_mm[0])


finite_or_not = st.one_of(
    st.floats(-60.0, 60.0), st.just(0.0), st.just(math.nan), st.just(math.inf),
    st.floats(-1e-12, 1e-12),
)


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(sorted(PROFILES)), st.sampled_from(sorted(POINT_MODELS)),
    finite_or_not, finite_or_not, st.booleans(),
)
def test_no_nan_or_inf_without_a_status(name, model, y1, y2, as32):
    dtype = np.float32 if as32 else np.float64
    inv = POINT_MODELS[model](PROFILES[name], None, np.array([y1], dtype), np.array([y2], dtype))
    ok = inv.status == Status.OK
    assert np.isfinite(inv.distance_mm[ok]).all() and np.isfinite(inv.offset_mm[ok]).all()
    assert np.isnan(inv.distance_mm[~ok]).all()


@settings(max_examples=200, deadline=None)
@given(finite_or_not, finite_or_not, finite_or_not, finite_or_not)
def test_line_model_never_returns_unflagged_nan(a1, a2, b1, b2):
    inv = line.invert(PROFILES["system1"], None, a1, a2, b1, b2)
    if inv.status == Status.OK:
        assert math.isfinite(float(inv.distance_mm)) and float(inv.distance_mm) > 0
    else:
        assert math.isnan(float(inv.distance_mm))
