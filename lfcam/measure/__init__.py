"""Measure: per-region blur geometry from a linear grey capture (docs/distance.md).

One entry point per method, each ``(profile, geom, image, region, ...) -> Measurement``:

* :func:`measure_lightfield` — the exact light-field fit of a point (or line) source;
* :func:`measure_lenslet` — the exact forward model fitted to per-lenslet moments (fast);
* :func:`measure_diameter` — the seed paper's signed footprint diameter;
* :func:`measure_refocus` — Hahne et al.'s depth from refocus (returns a distance directly).

Before them: :func:`prepare_geometry` (once per calibration and sensor size),
:func:`lenslet_stats` and :func:`find_regions` (once per capture), :func:`noise_sigma`.
"""

from lfcam.measure.base import Measurement, noise_sigma
from lfcam.measure.diameter import measure_diameter
from lfcam.measure.fastfit import measure_lenslet
from lfcam.measure.geometry import Geometry, prepare_geometry
from lfcam.measure.lenslets import LensletMap, LensletStats, lenslet_stats
from lfcam.measure.lightfield import measure_lightfield, measure_line
from lfcam.measure.refocus import measure_refocus
from lfcam.measure.regions import Region, find_regions

METHODS = ("lightfield", "lenslet", "diameter", "auto")

__all__ = [
    "METHODS", "Geometry", "LensletMap", "LensletStats", "Measurement", "Region",
    "find_regions", "lenslet_stats", "measure_diameter", "measure_lenslet", "measure_lightfield",
    "measure_line",
    "measure_refocus", "noise_sigma", "prepare_geometry",
]
