"""General sequential main lens: surfaces front to back, paraxial (cardinal) properties.

Frame (the profile contract for prescriptions): lengths in millimetres, optical axis z,
**z = 0 at the front vertex** of the first surface, +z toward the sensor. Object distances
are measured from the front vertex toward the object (positive in front of the lens), so an
object at distance ``d`` sits at ``z = -d``. The legacy singlet (:class:`lfcam.camera.MainLens`)
has its origin at the lens centre instead; :meth:`Prescription.from_singlet` documents the shift.

Every paraxial quantity here comes from a y–nu trace (a product of 2×2 refraction and
transfer matrices acting on (height, index × slope)), never from singlet formulas. The exact
(real-ray) focus helpers live in :mod:`lfcam.optics.raytrace` (``best_focus_z``,
``best_focus_object_distance``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from lfcam.errors import OpticsError, ProfileError

OBJECT_INDEX = 1.0  # object space is air (n = 1) for every prescription


@dataclass(frozen=True)
class Surface:
    """One refracting surface of a rotationally symmetric sequential lens.

    Parameters
    ----------
    radius_mm : float
        Vertex radius of curvature; positive when the centre of curvature lies at larger z.
        ``math.inf`` (either sign) is a flat surface.
    thickness_mm : float
        Axial distance from this vertex to the next one (ignored on the last surface). Zero
        and negative values are allowed (Zemax-style dummy surfaces, a stop placed behind a
        lens); rays follow the surface sequence regardless.
    refractive_index : float
        Refractive index of the medium AFTER the surface.
    semi_diameter_mm : float
        Clear semi-aperture; rays meeting the surface farther from the axis are vignetted.
        On the stop surface this is the stop radius.
    conic : float
        Conic constant k (0 sphere, −1 paraboloid, < −1 hyperboloid, > 0 oblate ellipsoid).
    stop : bool
        True on the aperture-stop surface (exactly one per prescription).
    focal_length_mm : float or None
        ``None`` (default): an ordinary refracting surface. A number makes this an **ideal
        (paraxial) surface**, like Zemax's ``PARAXIAL`` type: flat (``radius_mm`` must be
        infinite, sag 0), air on both sides, and it bends a ray that meets it at (x, y) in
        tangent space, slope s = (dx/dz, dy/dz): ``s_out = s_in − (x, y)·P(r)``, with
        ``P(r) = 1/f + a1·r² + a2·r⁴ + …`` (r² = x² + y²). Every object plane is imaged
        perfectly onto its Gaussian image plane when ``spherical`` is empty.
    spherical : tuple of float
        Ideal surface only: the aberration coefficients (a1, a2, …) of P(r), aᵢ in mm^−(2i+1)
        (a1 in mm⁻³, a2 in mm⁻⁵). A positive a1 makes the margin stronger than the paraxial
        zone (under-corrected spherical aberration, as a simple positive lens).

    Raises
    ------
    ProfileError
        On a non-finite or non-positive index or semi-diameter, a zero or NaN radius, a
        non-finite thickness, or a semi-diameter beyond the edge of the conic; for an ideal
        surface, a curved or conic surface, a zero or non-finite focal length, glass after it,
        or a non-finite aberration coefficient.
    """

    radius_mm: float
    thickness_mm: float
    refractive_index: float
    semi_diameter_mm: float
    conic: float = 0.0
    stop: bool = False
    focal_length_mm: float | None = None
    spherical: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        for name in ("radius_mm", "thickness_mm", "refractive_index", "semi_diameter_mm", "conic"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise ProfileError(f"{name} must be a number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if not isinstance(self.stop, (bool, np.bool_)):
            raise ProfileError(f"stop must be true or false, got {self.stop!r}")
        object.__setattr__(self, "stop", bool(self.stop))
        if math.isnan(self.radius_mm) or self.radius_mm == 0.0:
            raise ProfileError(f"radius_mm must be non-zero (inf = flat), got {self.radius_mm}")
        if not math.isfinite(self.thickness_mm):
            raise ProfileError(f"thickness_mm must be finite, got {self.thickness_mm}")
        if not (math.isfinite(self.refractive_index) and self.refractive_index >= 1.0):
            raise ProfileError(f"refractive_index must be >= 1, got {self.refractive_index}")
        if not (math.isfinite(self.semi_diameter_mm) and self.semi_diameter_mm > 0.0):
            raise ProfileError(f"semi_diameter_mm must be positive, got {self.semi_diameter_mm}")
        if not math.isfinite(self.conic):
            raise ProfileError(f"conic must be finite, got {self.conic}")
        c, h = self.curvature_per_mm, self.semi_diameter_mm
        if 1.0 - (1.0 + self.conic) * c * c * h * h <= 0.0:
            raise ProfileError(
                f"semi_diameter_mm {h} reaches beyond the edge of the surface "
                f"(radius {self.radius_mm}, conic {self.conic})"
            )
        self._check_ideal()

    def _check_ideal(self) -> None:
        """Validate the ideal-surface fields (see the class docstring)."""
        coeffs = tuple(self.spherical)
        for a in coeffs:
            if isinstance(a, bool) or not isinstance(a, (int, float, np.floating)):
                raise ProfileError(f"spherical: coefficients must be numbers, got {a!r}")
            if not math.isfinite(float(a)):
                raise ProfileError(f"spherical: coefficients must be finite, got {a!r}")
        object.__setattr__(self, "spherical", tuple(float(a) for a in coeffs))
        f = self.focal_length_mm
        if f is None:
            if self.spherical:
                raise ProfileError("spherical: only an ideal surface (focal_length_mm) takes it")
            return
        if isinstance(f, bool) or not isinstance(f, (int, float, np.floating)):
            raise ProfileError(f"focal_length_mm must be a number, got {f!r}")
        f = float(f)
        if not math.isfinite(f) or f == 0.0:
            raise ProfileError(f"focal_length_mm must be finite and non-zero, got {f}")
        object.__setattr__(self, "focal_length_mm", f)
        if not math.isinf(self.radius_mm) or self.conic != 0.0:
            raise ProfileError("an ideal surface (focal_length_mm) is flat: radius_mm = inf")
        if self.refractive_index != 1.0:
            raise ProfileError("an ideal surface (focal_length_mm) has air after it (index 1)")

    @property
    def is_ideal(self) -> bool:
        """True for an ideal (paraxial) surface."""
        return self.focal_length_mm is not None

    def ideal_power_per_mm(self, r2_mm2: np.ndarray | float) -> np.ndarray | float:
        """P(r) = 1/f + a1·r² + a2·r⁴ + … of an ideal surface at r² = ``r2_mm2``."""
        r2 = np.asarray(r2_mm2, dtype=np.float64)
        out = np.full(r2.shape, 1.0 / self.focal_length_mm)
        term = np.ones(r2.shape)
        for a in self.spherical:
            term = term * r2
            out = out + a * term
        return out if out.ndim else float(out)

    @property
    def curvature_per_mm(self) -> float:
        """Vertex curvature c = 1/R (0 for a flat surface)."""
        return 0.0 if math.isinf(self.radius_mm) else 1.0 / self.radius_mm

    def sag_mm(self, rho_mm: np.ndarray | float) -> np.ndarray | float:
        """Axial depth z(ρ) of the surface below its vertex at height ``rho_mm``."""
        c, k = self.curvature_per_mm, self.conic
        r2 = np.asarray(rho_mm, dtype=np.float64) ** 2
        out = c * r2 / (1.0 + np.sqrt(1.0 - (1.0 + k) * c * c * r2))
        return out if out.ndim else float(out)


@dataclass(frozen=True)
class Paraxial:
    """First-order (Gaussian) data of a prescription, all z in the front-vertex frame.

    Attributes
    ----------
    efl_mm : float
        Effective focal length 1/Φ (object space is air).
    bfl_mm : float
        Back focal length: last vertex → rear focal point F′.
    ffl_mm : float
        Front focal length: front vertex → front focal point F, measured toward +z
        (negative for a focal point in front of the lens).
    front_focal_z_mm, back_focal_z_mm : float
        z of F and F′.
    front_principal_z_mm, back_principal_z_mm : float
        z of the principal planes H and H′.
    entrance_pupil_z_mm, entrance_pupil_diameter_mm : float
        Paraxial image of the stop seen from object space.
    exit_pupil_z_mm, exit_pupil_diameter_mm : float
        Paraxial image of the stop seen from image space.
    image_index : float
        Refractive index of image space (the last surface's ``refractive_index``).
    """

    efl_mm: float
    bfl_mm: float
    ffl_mm: float
    front_focal_z_mm: float
    back_focal_z_mm: float
    front_principal_z_mm: float
    back_principal_z_mm: float
    entrance_pupil_z_mm: float
    entrance_pupil_diameter_mm: float
    exit_pupil_z_mm: float
    exit_pupil_diameter_mm: float
    image_index: float

    @property
    def f_number(self) -> float:
        """Infinity f-number: EFL / entrance-pupil diameter."""
        return self.efl_mm / self.entrance_pupil_diameter_mm


def _refraction(n_before: float, n_after: float, c: float) -> np.ndarray:
    """y–nu refraction matrix acting on (y, n·u): n′u′ = nu − y·(n′ − n)·c."""
    return np.array([[1.0, 0.0], [-(n_after - n_before) * c, 1.0]])


def _transfer(thickness_mm: float, n: float) -> np.ndarray:
    """y–nu transfer matrix: y′ = y + t·(nu)/n."""
    return np.array([[1.0, thickness_mm / n], [0.0, 1.0]])


@dataclass(frozen=True)
class Prescription:
    """A rotationally symmetric sequential lens: surfaces front to back, one aperture stop.

    Parameters
    ----------
    surfaces : tuple of Surface
        Front to back. Object space (before surface 0) is air, n = 1. The last surface's
        ``thickness_mm`` is ignored (the image gap belongs to the camera, not the lens).
    name : str
        Free label (e.g. the ``.zmx`` title).

    Raises
    ------
    ProfileError
        When there are no surfaces, the stop count is not one, or an entry is not a
        :class:`Surface`; messages name the surface index (0-based, front first).
    """

    surfaces: tuple[Surface, ...]
    name: str = ""

    def __post_init__(self) -> None:
        surfaces = tuple(self.surfaces)
        object.__setattr__(self, "surfaces", surfaces)
        if not surfaces:
            raise ProfileError("main_lens.surfaces: a prescription needs at least one surface")
        for i, s in enumerate(surfaces):
            if not isinstance(s, Surface):
                raise ProfileError(f"main_lens.surfaces[{i}]: expected a Surface, got {s!r}")
        stops = [i for i, s in enumerate(surfaces) if s.stop]
        if len(stops) != 1:
            where = f" (surfaces {stops})" if stops else ""
            raise ProfileError(
                f"main_lens.surfaces: exactly one surface must be the stop, found "
                f"{len(stops)}{where}"
            )
        nb = self.index_before
        for i, s in enumerate(surfaces):
            if s.is_ideal and nb[i] != 1.0:
                raise ProfileError(
                    f"main_lens.surfaces[{i}]: an ideal surface needs air before it too"
                )

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_singlet(
        cls,
        radius_mm: float,
        thickness_mm: float,
        refractive_index: float,
        pupil_diameter_mm: float,
    ) -> Prescription:
        """The seed paper's symmetric biconvex singlet as a prescription.

        Matches :class:`lfcam.camera.MainLens` and :mod:`lfcam.optics.trace` exactly: the
        aperture stop is the front surface itself, clipped at ρ ≤ D/2 on the sphere; the back
        surface is clipped where the two spheres meet (the lens edge). The legacy frame has
        its origin at mid-thickness, so legacy ``z`` = prescription ``z`` − T/2.

        Parameters
        ----------
        radius_mm : float
            R of both surfaces (front +R, back −R).
        thickness_mm : float
            Centre thickness T.
        refractive_index : float
            Glass index n.
        pupil_diameter_mm : float
            Clear aperture D at the front surface (the stop).

        Raises
        ------
        ProfileError
            If the numbers do not make a lens (see :class:`Surface`), or D/2 reaches the edge.
        """
        r, t = float(radius_mm), float(thickness_mm)
        edge_mm = math.sqrt(max(r * r - (r - 0.5 * t) ** 2, 0.0))
        if not 0.5 * pupil_diameter_mm < edge_mm:
            raise ProfileError(
                f"singlet: D/2 = {0.5 * pupil_diameter_mm} reaches the lens edge ({edge_mm:.4g} mm)"
            )
        front = Surface(r, t, refractive_index, 0.5 * pupil_diameter_mm, stop=True)
        back = Surface(-r, 0.0, 1.0, edge_mm)
        return cls((front, back), name="singlet")

    # ------------------------------------------------------------------ geometry

    @property
    def stop_index(self) -> int:
        """Index of the aperture-stop surface."""
        return next(i for i, s in enumerate(self.surfaces) if s.stop)

    @cached_property
    def vertex_z_mm(self) -> np.ndarray:
        """z of every surface vertex (front vertex = 0)."""
        t = [s.thickness_mm for s in self.surfaces[:-1]]
        out = np.concatenate([[0.0], np.cumsum(t)])
        out.setflags(write=False)
        return out

    @property
    def last_vertex_z_mm(self) -> float:
        """z of the last (rear) vertex; the profile's ``gap_mm`` is measured from here."""
        return float(self.vertex_z_mm[-1])

    @property
    def index_before(self) -> tuple[float, ...]:
        """Refractive index of the medium before each surface."""
        return (OBJECT_INDEX,) + tuple(s.refractive_index for s in self.surfaces[:-1])

    @property
    def image_index(self) -> float:
        """Refractive index of image space."""
        return self.surfaces[-1].refractive_index

    # ------------------------------------------------------------------ paraxial

    def _matrix(self, first: int, last: int) -> np.ndarray:
        """y–nu matrix from just before surface ``first`` (on its vertex plane, before its
        refraction) to just after surface ``last``."""
        m = np.eye(2)
        nb = self.index_before
        for i in range(first, last + 1):
            s = self.surfaces[i]
            if i > first:
                prev = self.surfaces[i - 1]
                m = _transfer(prev.thickness_mm, prev.refractive_index) @ m
            if s.is_ideal:  # thin lens in air: nu' = nu - y/f
                m = np.array([[1.0, 0.0], [-1.0 / s.focal_length_mm, 1.0]]) @ m
            else:
                m = _refraction(nb[i], s.refractive_index, s.curvature_per_mm) @ m
        return m

    def system_matrix(self) -> np.ndarray:
        """y–nu ABCD matrix from the front vertex plane (object side) to the last vertex plane
        (image side), acting on (y, n·u)."""
        return self._matrix(0, len(self.surfaces) - 1)

    @cached_property
    def paraxial(self) -> Paraxial:
        """First-order data from y–nu traces (see :class:`Paraxial`).

        Raises
        ------
        OpticsError
            For an afocal system (zero power), where focal points do not exist.
        """
        (a, b), (c, d) = self.system_matrix()
        if c == 0.0:
            raise OpticsError("the prescription is afocal (zero power): no focal points")
        n_img = self.image_index
        z_last = self.last_vertex_z_mm
        efl = -1.0 / c  # Φ = −C; object space n = 1
        bfl = -a * n_img / c
        ffl = d / c
        back_focal = z_last + bfl
        front_focal = ffl
        back_principal = back_focal - n_img * efl
        front_principal = front_focal + efl

        k = self.stop_index
        stop = self.surfaces[k]
        # entrance pupil: stop seen through surfaces 0..k-1 (object space n = 1)
        if k == 0:
            front = np.eye(2)
        else:
            front = _transfer(
                self.surfaces[k - 1].thickness_mm, self.surfaces[k - 1].refractive_index
            ) @ self._matrix(0, k - 1)
        (fa, fb), _ = front
        enp_z = fb / fa  # axial object point whose image is the stop centre
        enp_d = 2.0 * stop.semi_diameter_mm / abs(fa)  # stop height / (A of the conjugates)
        # exit pupil: stop seen through surfaces k..last (image space n′)
        (pa, pb), (pc, pd) = self._matrix(k, len(self.surfaces) - 1)
        if pd == 0.0:
            exp_z = math.inf
            exp_d = math.inf
        else:
            gap = -pb * n_img / pd  # last vertex → exit pupil
            exp_z = z_last + gap
            exp_d = 2.0 * stop.semi_diameter_mm * abs(pa + gap * pc / n_img)
        return Paraxial(
            efl_mm=float(efl),
            bfl_mm=float(bfl),
            ffl_mm=float(ffl),
            front_focal_z_mm=float(front_focal),
            back_focal_z_mm=float(back_focal),
            front_principal_z_mm=float(front_principal),
            back_principal_z_mm=float(back_principal),
            entrance_pupil_z_mm=float(enp_z),
            entrance_pupil_diameter_mm=float(enp_d),
            exit_pupil_z_mm=float(exp_z),
            exit_pupil_diameter_mm=float(exp_d),
            image_index=float(n_img),
        )

    @property
    def efl_mm(self) -> float:
        """Effective focal length (paraxial)."""
        return self.paraxial.efl_mm

    @property
    def f_number(self) -> float:
        """Infinity f-number, EFL / entrance-pupil diameter (paraxial)."""
        return self.paraxial.f_number

    def image_plane_z_for(self, object_distance_mm: float) -> float:
        """Paraxial image plane z of an axial object ``object_distance_mm`` before the front vertex.

        ``math.inf`` gives the rear focal plane.

        Raises
        ------
        OpticsError
            If the distance is not positive, or the object is at or inside the front focal
            point (no real image).
        """
        dist = float(object_distance_mm)
        if math.isnan(dist) or dist <= 0.0:
            raise OpticsError(f"object distance must be positive, got {object_distance_mm}")
        if self.paraxial.efl_mm <= 0.0:
            raise OpticsError("the prescription diverges (EFL <= 0): no real image")
        (a, b), (c, d) = self.system_matrix()
        n_img = self.image_index
        if math.isinf(dist):
            gap = -a * n_img / c
        else:
            denominator = c * dist + d
            gap = math.inf if denominator == 0.0 else -n_img * (a * dist + b) / denominator
        if not math.isfinite(gap) or -dist >= self.paraxial.front_focal_z_mm:
            raise OpticsError(
                f"object at {dist} mm is at or inside the front focal point "
                f"(F at z = {self.paraxial.front_focal_z_mm:.4f} mm): no real image"
            )
        return self.last_vertex_z_mm + gap

    def image_distance_for(self, object_distance_mm: float) -> float:
        """Paraxial image distance behind the LAST vertex (the profile's ``gap_mm``) for an
        axial object ``object_distance_mm`` before the front vertex. See
        :meth:`image_plane_z_for`."""
        return self.image_plane_z_for(object_distance_mm) - self.last_vertex_z_mm

    def object_distance_for(self, image_plane_z_mm: float) -> float:
        """Paraxial object distance (before the front vertex) in focus at ``image_plane_z_mm``.

        Returns ``inf`` when the plane is at or in front of the rear focal point F′ (the
        legacy :meth:`lfcam.camera.MainLens.focus_for_d_in` convention).
        """
        z = float(image_plane_z_mm)
        if math.isnan(z):
            raise OpticsError("image plane z is NaN")
        if z <= self.paraxial.back_focal_z_mm:
            return math.inf
        (a, b), (c, d) = self.system_matrix()
        n_img = self.image_index
        gap = z - self.last_vertex_z_mm
        denominator = a * n_img + gap * c
        if denominator == 0.0:
            return math.inf
        return float(-(b * n_img + gap * d) / denominator)

    # ------------------------------------------------------------------ real stop circle

    @property
    def stop_plane_z_mm(self) -> float:
        """z of the plane of the stop's edge circle: the stop vertex plus the stop surface's
        sag at its semi-diameter (the vertex plane for a flat stop; the seed singlet's rim
        plane, where its aperture really is, for a stop on a curved surface)."""
        k = self.stop_index
        s = self.surfaces[k]
        return float(self.vertex_z_mm[k] + s.sag_mm(s.semi_diameter_mm))

    @cached_property
    def stop_pupils(self) -> tuple[float, float, float, float]:
        """Paraxial pupils of the stop's edge circle: ``(entrance_z, entrance_diameter,
        exit_z, exit_diameter)``.

        The edge circle sits on the stop surface, so object-space rays reach it through the
        surfaces in front of the stop only, and leave it through the surfaces behind it; its
        plane (:attr:`stop_plane_z_mm`) is imaged through those. For a flat stop this is
        :attr:`paraxial`'s pupils; for the seed singlet (stop = its front surface) the entrance
        pupil is the rim circle itself and the exit pupil the rim plane imaged by the back
        surface (the legacy ``MainLens.exit_pupil_z_mm``).
        """
        k = self.stop_index
        last = len(self.surfaces) - 1
        sd = self.surfaces[k].semi_diameter_mm
        z_s = self.stop_plane_z_mm
        vz = self.vertex_z_mm
        n_img = self.image_index
        if k == 0:
            enp_z, enp_d = z_s, 2.0 * sd
        else:
            m = _transfer(z_s - vz[k - 1], self.surfaces[k - 1].refractive_index) @ self._matrix(
                0, k - 1
            )
            (fa, fb), _ = m
            enp_z = fb / fa
            enp_d = 2.0 * sd / abs(fa)
        n_k = self.surfaces[k].refractive_index
        if k == last:
            exp_z, exp_d = z_s, 2.0 * sd
        else:
            m = self._matrix(k + 1, last) @ _transfer(vz[k + 1] - z_s, n_k)
            (pa, pb), (pc, pd) = m
            if pd == 0.0:
                exp_z, exp_d = math.inf, math.inf
            else:
                gap = -pb * n_img / pd
                exp_z = vz[last] + gap
                exp_d = 2.0 * sd * abs(pa + gap * pc / n_img)
        return float(enp_z), float(enp_d), float(exp_z), float(exp_d)


def ideal_lens(
    focal_length_mm: float,
    f_number: float | None,
    principal_z_mm: float = 0.0,
    exit_pupil_z_mm: float | None = None,
    spherical: tuple[float, ...] = (),
    name: str = "ideal lens",
    exit_pupil_diameter_mm: float | None = None,
) -> Prescription:
    """A first-order lens as a prescription of ideal surfaces: the black-box main lens.

    Surfaces: 0, a flat dummy at the lens front (z = 0, where object distances start); 1, an
    ideal surface (:class:`Surface` with ``focal_length_mm``) at ``principal_z_mm`` (both
    principal planes; a thick lens's H–H′ separation is a shift of image space, which the MLA
    distance absorbs); 2, the aperture stop, placed in image space at the exit pupil
    (``exit_pupil_z_mm``; default: on the ideal surface), so the exit pupil *is* the stop and
    the entrance pupil its image through the ideal surface. The stop radius gives the stated
    infinity f-number (EFL / entrance-pupil diameter). The stop's thickness may be negative
    (an exit pupil in front of the ideal surface is a virtual one; rays are traced along
    their image-space lines to it).

    Parameters
    ----------
    focal_length_mm : float
        EFL f (> 0).
    f_number : float or None
        Infinity f-number f / D_entrance (> 0); or ``None`` and give
        ``exit_pupil_diameter_mm`` (the stop's diameter) instead.
    principal_z_mm : float
        Lens front → principal plane.
    exit_pupil_z_mm : float or None
        z of the exit pupil (front-vertex frame); ``None``: the principal plane.
    spherical : tuple of float
        Aberration coefficients of the ideal surface (see :class:`Surface`).
    name : str
        Label.
    exit_pupil_diameter_mm : float or None
        The aperture given on the image side (exclusive with ``f_number``).

    Raises
    ------
    ProfileError
        On a non-positive focal length, f-number or pupil diameter, or an exit pupil in the
        rear focal plane (the entrance pupil would be at infinity, no f-number can be set).
    """
    f = float(focal_length_mm)
    if not (math.isfinite(f) and f > 0.0):
        raise ProfileError(f"main_lens.focal_length_mm must be positive, got {focal_length_mm}")
    if (f_number is None) == (exit_pupil_diameter_mm is None):
        raise ProfileError("ideal lens: give exactly one of f_number and exit_pupil_diameter_mm")
    aperture = float(f_number if f_number is not None else exit_pupil_diameter_mm)
    if not (math.isfinite(aperture) and aperture > 0.0):
        raise ProfileError(
            f"main_lens.f_number / exit pupil diameter must be positive, got {aperture}")
    h = float(principal_z_mm)
    z_xp = h if exit_pupil_z_mm is None else float(exit_pupil_z_mm)
    if not (math.isfinite(h) and math.isfinite(z_xp)):
        raise ProfileError("ideal lens: the principal plane and exit pupil must be finite")
    big = 20.0 * f  # dummy and ideal surfaces never vignette; the stop does
    # entrance pupil = the stop imaged backward by the ideal surface: height scale 1/|A|
    e = z_xp - h  # ideal surface → stop (image space)
    a = 1.0 - e / f
    if abs(a) < 1e-9:
        raise ProfileError(
            "ideal lens: the exit pupil lies in the rear focal plane (entrance pupil at infinity)"
        )
    stop_semi = 0.5 * (f / aperture) * abs(a) if f_number is not None else 0.5 * aperture
    front = Surface(math.inf, h, 1.0, big)
    lens = Surface(math.inf, e, 1.0, big, focal_length_mm=f, spherical=tuple(spherical))
    stop = Surface(math.inf, 0.0, 1.0, stop_semi, stop=True)
    return Prescription((front, lens, stop), name=name)
