"""Quality gates of a white-image calibration: coverage, lattice residual, model misfit.

A calibration states how much of the lattice it measured, how well its lattice model fits
and how well the micro-image model fits the white image. :func:`assess` turns these into a
:class:`Quality` with a verdict ``ok`` or ``poor`` and the reasons; the limits below are
justified in docs/robustness.md ("Calibration quality gates", measured with
``python benchmarks/calibration_quality.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: lenses measured / fully visible lattice sites found (measured + unconverged + dim +
#: outlier) must reach this
MIN_COVERAGE = 0.9
#: lattice residual RMS, as a fraction of the pitch
MAX_RESIDUAL_REL_PITCH = 0.02
#: relative RMS misfit of the global disc model of the micro-images
MAX_MISFIT = 0.15
#: rejection reasons that mean "a fully visible lens that was not measured"
LOST_REASONS = ("unconverged", "dim", "outlier")


@dataclass(frozen=True)
class Quality:
    """Quality figures and verdict of one calibration.

    Attributes
    ----------
    coverage : float
        Lenses measured / fully visible lattice sites found.
    expected : int
        Fully visible lattice sites found (measured + lost).
    residual_rms_px : float
    residual_rel_pitch : float
        ``residual_rms_px / pitch_px``.
    misfit : float or None
        Relative misfit of the disc model (None when the calibration does not state it).
    verdict : str
        ``ok`` or ``poor``.
    reasons : tuple of str
        One short sentence per failed gate (empty when ``ok``).
    """

    coverage: float
    expected: int
    residual_rms_px: float
    residual_rel_pitch: float
    misfit: float | None
    verdict: str
    reasons: tuple[str, ...]

    def to_dict(self, accepted_poor: bool = False) -> dict:
        """The ``quality`` block of the calibration JSON."""
        return {"coverage": round(self.coverage, 6), "expected_lenses": self.expected,
                "residual_rms_px": self.residual_rms_px,
                "residual_rel_pitch": round(self.residual_rel_pitch, 6),
                "misfit": self.misfit, "verdict": self.verdict, "reasons": list(self.reasons),
                "limits": {"min_coverage": MIN_COVERAGE,
                           "max_residual_rel_pitch": MAX_RESIDUAL_REL_PITCH,
                           "max_misfit": MAX_MISFIT},
                "accepted_poor": bool(accepted_poor)}


def assess(cal) -> Quality:
    """Measure the quality gates of a :class:`~lfcam.calibrate.Calibration`.

    Parameters
    ----------
    cal : Calibration

    Returns
    -------
    Quality
    """
    lost = sum(int(cal.rejected.get(r, 0)) for r in LOST_REASONS)
    expected = cal.n_lenses + lost
    coverage = cal.n_lenses / expected if expected else 0.0
    rel = cal.residual_rms_px / cal.pitch_px
    m = cal.diagnostics.get("disc_rel_residual")
    misfit = float(m) if isinstance(m, (int, float)) and math.isfinite(m) else None
    reasons = []
    if coverage < MIN_COVERAGE:
        reasons.append(f"coverage {coverage:.3f} ({cal.n_lenses} of {expected} fully visible "
                       f"lenses measured; limit {MIN_COVERAGE})")
    if not rel <= MAX_RESIDUAL_REL_PITCH:
        reasons.append(f"lattice residual {cal.residual_rms_px:.3f} px = {rel:.4f} pitch "
                       f"(limit {MAX_RESIDUAL_REL_PITCH} pitch = "
                       f"{MAX_RESIDUAL_REL_PITCH * cal.pitch_px:.3f} px)")
    if misfit is not None and misfit > MAX_MISFIT:
        reasons.append(f"micro-image model misfit {misfit:.3f} (limit {MAX_MISFIT})")
    return Quality(coverage=coverage, expected=expected, residual_rms_px=cal.residual_rms_px,
                   residual_rel_pitch=rel, misfit=misfit,
                   verdict="poor" if reasons else "ok", reasons=tuple(reasons))


#: largest relative disagreement between the profile's predicted micro-image pitch and the
#: calibration's measured pitch
MAX_PITCH_MISMATCH = 0.05


def predicted_pitch_px(profile, d_in_mm: float) -> float:
    """Micro-image centre spacing (px) the profile predicts: the lenslet pitch projected from
    the exit-pupil centre onto the sensor, ``p·(1 + f_x / (d_in − z_exit))`` / pixel pitch."""
    p = profile.mla.pitch_mm / profile.sensor.pixel_pitch_mm
    try:
        lever = d_in_mm - float(profile.main_lens.exit_pupil_z_mm)
    except (AttributeError, ArithmeticError, ValueError):
        return p
    if not (math.isfinite(lever) and lever > 0):
        return p
    return p * (1.0 + profile.mla.focal_length_mm / lever)


def check_profile_pitch(profile, cal, d_in_mm: float) -> None:
    """Refuse a profile whose MLA/sensor disagree with the calibration's measured pitch.

    Parameters
    ----------
    profile : CameraProfile
    cal : Calibration
    d_in_mm : float
        MLA distance in use (the calibration's, else the profile's).

    Raises
    ------
    CalibrationMismatchError
        Predicted and measured micro-image pitch differ by more than ``MAX_PITCH_MISMATCH``.
    """
    from lfcam.errors import CalibrationMismatchError

    want = predicted_pitch_px(profile, d_in_mm)
    got = float(cal.pitch_px)
    if not (math.isfinite(want) and want > 0) or abs(got / want - 1.0) > MAX_PITCH_MISMATCH:
        raise CalibrationMismatchError(
            f"profile {profile.name!r} predicts a micro-image pitch of {want:.4g} px "
            f"(mla.pitch_mm {profile.mla.pitch_mm:g} / sensor.pixel_pitch_mm "
            f"{profile.sensor.pixel_pitch_mm:g}, projected from the exit pupil) but "
            f"{cal.source or 'the calibration'} measured {got:.4g} px "
            f"(limit ±{MAX_PITCH_MISMATCH:.0%}): wrong profile for this camera")
