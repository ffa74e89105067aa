"""Sensor model: exposure, Bayer mosaic, photon and read noise, quantisation, hot pixels."""

from __future__ import annotations

import numpy as np

from lfcam.sim.scene import SensorEffects

# colour index (0 R, 1 G, 2 B) of the 2×2 CFA cells [[top-left, top-right], [bottom-left, ...]]
CFA = {
    "RGGB": ((0, 1), (1, 2)),
    "BGGR": ((2, 1), (1, 0)),
    "GRBG": ((1, 0), (2, 1)),
    "GBRG": ((1, 2), (0, 1)),
}


def cfa_gain(bayer: str, gains: tuple[float, float, float], height: int, width: int) -> np.ndarray:
    """Per-pixel gain of a Bayer mosaic (all ones for ``"none"``)."""
    if bayer == "none":
        return np.ones((height, width))
    pattern = np.array(CFA[bayer])
    colour = pattern[np.arange(height)[:, None] % 2, np.arange(width)[None, :] % 2]
    return np.asarray(gains, dtype=np.float64)[colour]


def apply_sensor(
    signal: np.ndarray,
    effects: SensorEffects,
    bayer: str,
    bit_depth: int,
    black_level: int,
    white_level: int,
    exposure_scale: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Turn a noiseless signal into raw digital numbers.

    ``signal·exposure_scale`` is the fraction of full scale (1 = white level) before colour
    gains. With photon noise the electrons ``fraction·full_well_e`` are Poisson-distributed;
    read noise adds Gaussian electrons. Values are rounded, offset by the black level and
    clipped to ``[0, 2**bit_depth − 1]`` (and to the white level).

    Returns
    -------
    ndarray of uint16
    """
    h, w = signal.shape
    frac = signal * exposure_scale * cfa_gain(bayer, effects.bayer_gains, h, w)
    electrons = frac * effects.full_well_e
    if effects.photon_noise:
        electrons = rng.poisson(np.maximum(electrons, 0.0)).astype(np.float64)
    if effects.read_noise_e > 0:
        electrons = electrons + rng.normal(0.0, effects.read_noise_e, electrons.shape)
    dn = black_level + electrons / effects.full_well_e * (white_level - black_level)
    if effects.hot_pixels:
        n = min(effects.hot_pixels, h * w)
        where = rng.choice(h * w, size=n, replace=False)
        dn.ravel()[where] = black_level + effects.hot_value * (white_level - black_level)
    top = min(2**bit_depth - 1, white_level)
    return np.clip(np.rint(dn), 0, top).astype(np.uint16)
