"""``hahne``: refocusing distance of a standard plenoptic camera (Hahne et al., the seed's [14]).

Paraxial ray model with the parameters PlenoptiSign takes. A refocused pixel at shift ``a``
combines rays through lenslets ``j0`` and ``j1 = j0 + a(M − 1)`` seen from the two extreme
micro-image pixels ``i = ±(M − 1)/2``. Each ray is fixed by a lenslet centre ``s = j·p_m`` and a
pixel ``u = s(1 + f_s/d_A) + i·p_p`` (the micro-image centre is the chief ray through the exit
pupil, a distance ``d_A`` before the MLA):

    image-side slope   m = (s − u)/f_s
    main-lens height   U = m·b_U + s             (b_U: H2 → MLA)
    object-side slope  q = (m·f_U − U)/f_U

The two object-side rays ``U + q·x`` meet at ``x`` (from H1); the refocusing distance,
measured like PlenoptiSign's ``d`` from the MLA plane, is ``x + b_U + HH``. The depth-of-field
borders repeat this with rays through the pixel and lenslet edges (``u ± p_p/2``,
``s ± p_m/2``). Where the image-side crossing ``b`` reaches ``f_U`` the plane is at infinity.

``hh`` (lenslet principal-plane spacing) and ``f_num`` are accepted for parity with
PlenoptiSign; neither enters the refocusing distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.errors import OpticsError

ROUND_DIGITS = 4  # the lenslet index j0 is rounded to 4 decimals, as PlenoptiSign does


@dataclass(frozen=True)
class HahneParameters:
    """Standard-plenoptic-camera parameters (millimetres; ``M`` in pixels).

    Parameters
    ----------
    pp : pixel pitch. fs : lenslet focal length. hh : lenslet principal-plane spacing.
    pm : lenslet pitch. dA : exit pupil → MLA distance. fU : main-lens focal length.
    HH : main-lens principal-plane spacing (H1 → H2). df : focused object distance,
    measured from the MLA plane (``inf`` allowed). f_num : main-lens f-number.
    M : 1-D micro-image size in pixels.
    """

    pp: float
    fs: float
    pm: float
    dA: float
    fU: float
    HH: float
    df: float
    M: float
    hh: float = 0.0
    f_num: float = math.nan

    @property
    def image_distance_mm(self) -> float:
        """b_U, H2 → MLA: the paraxial image of ``df`` (``fU`` at infinity)."""
        if math.isinf(self.df):
            return self.fU
        if self.df <= self.fU:
            return math.inf
        total = self.df - self.HH  # a_U + b_U
        disc = total * total - 4.0 * self.fU * total
        if disc < 0.0:
            raise OpticsError(f"focus distance df = {self.df} mm is too close to be imaged")
        return 0.5 * (total - math.sqrt(disc))


class Refocus(NamedTuple):
    """Refocusing distance and depth-of-field borders (mm from the MLA plane; inf allowed)."""

    distance_mm: np.ndarray
    far_mm: np.ndarray
    near_mm: np.ndarray


def _crossing(u0, q0, u1, q1):
    """x where the lines ``u0 + q0·x`` and ``u1 + q1·x`` meet."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return (u0 - u1) / (q1 - q0)


def refocus_distance(params: HahneParameters, a) -> Refocus:
    """Refocusing distance and DoF borders for shift(s) ``a`` (vectorised).

    Parameters
    ----------
    params : HahneParameters
    a : array_like
        Refocusing shift parameter(s).

    Returns
    -------
    Refocus
    """
    a = np.asarray(a, dtype=np.float64)
    pp, fs, pm, d_a = params.pp, params.fs, params.pm, params.dA
    f_u, b_u = params.fU, params.image_distance_mm
    c = 0.5 * (params.M - 1.0)
    j0 = -np.round(a * c, ROUND_DIGITS)
    j1 = a * (params.M - 1.0) + j0
    lenses = (j0 * pm, j1 * pm)
    pixels = (c, -c)

    def ray(s, u, s_edge=0.0):
        m = (s - u) / fs
        height = m * b_u + s + s_edge
        return height, (m * f_u - height) / f_u, m

    centre, upper, lower = [], [], []
    for s, i in zip(lenses, pixels, strict=True):
        u = s * (1.0 + fs / d_a) + i * pp
        centre.append(ray(s, u))
        upper.append(ray(s, u + 0.5 * pp, 0.5 * pm))
        lower.append(ray(s, u - 0.5 * pp, -0.5 * pm))
    base = b_u + params.HH

    def distance(r0, r1, s0, s1):
        # object side (returned) and image side (decides whether the plane is at infinity)
        x_obj = _crossing(r0[0], r0[1], r1[0], r1[1])
        b_new = b_u - _crossing(s0, r0[2], s1, r1[2])
        return np.where(b_new > f_u, x_obj + base, np.inf)

    s0, s1 = lenses
    d = distance(centre[0], centre[1], s0, s1)
    far = distance(upper[0], lower[1], s0 + 0.5 * pm, s1 - 0.5 * pm)
    near = distance(lower[0], upper[1], s0 - 0.5 * pm, s1 + 0.5 * pm)
    return Refocus(d, far, near)


def shift_for_distance(params: HahneParameters, distance_from_mla_mm) -> np.ndarray:
    """Shift ``a`` that refocuses onto an object ``distance_from_mla_mm`` away (closed form).

    Uses the image-side form of the same model: the refocused image plane is
    ``b = b_U + Δ`` with ``Δ = a·p_m / (p_p/f_s − a·p_m/d_A)``, and ``b`` is the paraxial image of
    the object, so ``a = Δ·p_p / (f_s·p_m·(1 + Δ/d_A))``.
    """
    d = np.asarray(distance_from_mla_mm, dtype=np.float64)
    b_u = params.image_distance_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        a_obj = d - b_u - params.HH
        b_new = np.where(np.isinf(d), params.fU, 1.0 / (1.0 / params.fU - 1.0 / a_obj))
        delta = b_new - b_u
        return delta * params.pp / (params.fs * params.pm * (1.0 + delta / params.dA))


def parameters_for(profile: CameraProfile, d_in_mm: float | None = None) -> HahneParameters:
    """Hahne parameters of one of our cameras.

    ``dA`` is the MLA's distance to the paraxial exit pupil, ``HH`` the spacing H1 → H2, ``df``
    the paraxial in-focus object distance measured from the MLA, and ``M`` the micro-image
    pitch in pixels, ``p_m(1 + f_s/d_A)/p_p``.
    """
    lens = profile.main_lens
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    f = lens.focal_length_mm
    b_u = d_in - lens.back_principal_z_mm
    spacing = lens.back_principal_z_mm - lens.front_principal_z_mm
    df = math.inf if b_u <= f else 1.0 / (1.0 / f - 1.0 / b_u) + spacing + b_u
    d_a = d_in - lens.exit_pupil_z_mm
    fs, pm, pp = profile.mla.focal_length_mm, profile.mla.pitch_mm, profile.sensor.pixel_pitch_mm
    return HahneParameters(
        pp=pp, fs=fs, pm=pm, dA=d_a, fU=f, HH=spacing, df=df,
        M=pm * (1.0 + fs / d_a) / pp, hh=0.0, f_num=lens.f_number,
    )


def mla_to_front_vertex_mm(profile: CameraProfile, d_in_mm: float | None = None) -> float:
    """Add to a ``distance_mm`` to get the same plane measured from the MLA (Hahne's ``d``)."""
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    return d_in - profile.main_lens.front_vertex_z_mm
