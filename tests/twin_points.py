"""Two point sources behind a 1 m focus whose blurs touch or overlap (the touching-blur and
overlapping-blur tests' captures, rendered once a process)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from lfcam import distance
from lfcam.camera import load_profile
from lfcam.measure import lenslet_stats
from lfcam.measure.noise import capture_noise
from lfcam.sim.capture import apply_overrides, simulate
from lfcam.sim.geometry import truth_geometry
from lfcam.sim.scene import scene_from_dict
from lfcam.status import RegionStatus

SIZE = 1024
CAMERA = {"mla": {"focus_mm": 1000.0}, "sensor": {"width_px": SIZE, "height_px": SIZE}}
NOISE = {"photon_noise": True, "full_well_e": 20000.0, "read_noise_e": 3.0}  # focus_grid's
_CAPTURES: dict = {}


def render_pair(apart: float, sensor: bool = False, system: str = "system2",
                distances: tuple[float, float] = (1400.0, 1500.0), first_line_mm: float = 0.0,
                only: int | None = None, second_line_mm: float = 0.0) -> tuple:
    """``system`` focused at 1 m, points at ``distances`` (system 2, 1 400 and 1 500 mm
    behind focus: blurs ~290 and ~305 px across) ``apart`` × 1/1000 of their distance off the
    axis on either side (render seed 7, 10⁶ rays a source, brightest pixel at half of full
    scale): on system 2 18 puts their light centroids 259 px apart, 16.5 237 px, 14 201 px, 13
    187 px. ``sensor``: the focus grid's sensor noise (photon noise at a 20 000 e⁻ full well,
    which the profile then states, 3 e⁻ read noise); else the rays' own noise alone.
    ``first_line_mm`` L > 0: the first source a line of L × its distance / 1000 mm, across the
    pair's line, of the same total light (benchmarks/overlapping_blurs.py
    ``--first-line-mm``); ``second_line_mm``: the second a line along the pair's line, across
    the first (a T), as bright per mm as a first line of that length. ``only`` = k: source k
    alone, the other left out of the scene (its light by itself). (profile, geometry, image,
    lenslet statistics, pixel noise, truth, white level)."""
    key = (apart, sensor, system, distances, first_line_mm, only, second_line_mm)
    if key not in _CAPTURES:
        base = load_profile(system)
        prof = apply_overrides(base, CAMERA)
        prof = prof.with_d_in(prof.d_in_mm)
        if sensor:  # (the fits told the renders' full well)
            prof = replace(prof, sensor=replace(prof.sensor, full_well_e=NOISE["full_well_e"]))
        objects = [{"type": "point", "distance_mm": d, "position_mm": [0.0, s * apart * d / 1000]}
                   for d, s in zip(distances, (-1.0, 1.0), strict=True)]
        if first_line_mm > 0:
            half = 0.5 * first_line_mm * distances[0] / 1000
            y = -apart * distances[0] / 1000
            objects[0] = {"type": "line", "distance_mm": distances[0], "intensity": 0.5 / half,
                          "start_mm": [-half, y], "end_mm": [half, y]}
        if second_line_mm > 0:
            half = 0.5 * second_line_mm * distances[1] / 1000
            y = apart * distances[1] / 1000
            per_mm = 1000.0 / (second_line_mm * distances[0])
            objects[1] = {"type": "line", "distance_mm": distances[1], "intensity": per_mm,
                          "start_mm": [0.0, y - half], "end_mm": [0.001, y + half]}
        if only is not None:
            objects = [objects[only]]
        scene = {"seed": 7, "rays_per_source": 1_000_000, "camera": CAMERA,
                 "exposure": {"peak": 0.5}, "objects": objects}
        if sensor:
            scene["sensor"] = NOISE
        raw, used, truth = simulate(base, scene_from_dict(scene))
        image = raw.astype(np.float64) - used.sensor.black_level
        geom = truth_geometry(prof, (SIZE, SIZE))
        white = float(used.sensor.white_level - used.sensor.black_level)
        stats = lenslet_stats(image, geom.lmap)
        capture_noise(image, geom.lmap, geom.pitch_px, stats,
                      sensor_gain=distance.sensor_gain(prof, white))
        _CAPTURES[key] = (prof, geom, image, stats, distance.noise_sigma(image), truth,
                                    white)
    return _CAPTURES[key]


def errors_by_source(run, truth) -> dict:
    """{truth source index: (relative error, relative σ)} of a distance run whose regions
    are all ``ok``, each region taken for the source whose light centroid is nearest its
    own; both sources must be answered."""
    out = {}
    for r in run.regions:
        assert r.status == RegionStatus.OK, r
        k = int(np.argmin([np.hypot(r.x_px - s["centroid_px"][0], r.y_px - s["centroid_px"][1])
                           for s in truth["sources"]]))
        d = truth["sources"][k]["distance_mm"]
        out[k] = (r.distance_mm / d - 1.0, r.uncertainty_mm / d)
    assert set(out) == {0, 1}
    return out

