"""Unpack speed of packed Lytro raws at full sensor size, against naive baselines.

Run: ``python benchmarks/io.py`` from the repository root. Prints one table: best of N
runs for our vectorised unpackers and for two baselines measured in the same run —
a generic bit-stream decoder (``np.unpackbits`` + weighted sum, vectorised but naive) and a
pure-Python per-pixel loop timed on a slice and scaled to the full frame.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from lfcam.io.packing import unpack_10bit_le, unpack_12bit_be  # noqa: E402


def best(fn, n=5):
    t = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return min(t)


def bitstream_10bit(buf: np.ndarray, w: int, h: int) -> np.ndarray:
    """Generic decoder: explode every byte to bits, regroup per pixel."""
    g = buf.reshape(-1, 5)
    hi = np.unpackbits(g[:, :4, None], axis=2)  # (n, 4, 8) MSB first
    lo = np.unpackbits(g[:, 4:5], axis=1, bitorder="little").reshape(-1, 4, 2)
    bits = np.concatenate([hi, lo[:, :, ::-1]], axis=2).astype(np.uint16)
    return (bits @ (1 << np.arange(9, -1, -1, dtype=np.uint16))).reshape(h, w)


def python_loop_10bit(buf: bytes, n_px: int) -> list[int]:
    out = []
    for g in range(0, n_px // 4 * 5, 5):
        low = buf[g + 4]
        for k in range(4):
            out.append((buf[g + k] << 2) | ((low >> (2 * k)) & 3))
    return out


def main() -> None:
    rng = np.random.default_rng(0)
    w, h = 7728, 5368
    buf = rng.integers(0, 256, size=w * h * 5 // 4, dtype=np.uint8)
    raw = buf.tobytes()
    fw = 3280
    buf12 = rng.integers(0, 256, size=fw * fw * 3 // 2, dtype=np.uint8).tobytes()

    ours = best(lambda: unpack_10bit_le(raw, w, h))
    ref = unpack_10bit_le(raw, w, h)
    rows = 64
    generic = best(lambda: bitstream_10bit(buf[: w * rows * 5 // 4], w, rows), 3) * h / rows
    assert np.array_equal(bitstream_10bit(buf[: w * rows * 5 // 4], w, rows), ref[:rows])
    n_loop = w * 4
    loop = best(lambda: python_loop_10bit(raw, n_loop), 2) * (w * h) / n_loop
    assert python_loop_10bit(raw, n_loop) == ref[:4].reshape(-1).tolist()
    ours12 = best(lambda: unpack_12bit_be(buf12, fw, fw))

    print(f"{'case':52s} {'seconds':>9s} {'ratio':>8s}")
    print(f"{'Illum 7728x5368 10-bit: lfcam unpack_10bit_le':52s} {ours:9.3f} {1.0:8.1f}")
    print(f"{'  baseline np.unpackbits bit-stream (scaled)':52s} {generic:9.3f} "
          f"{generic / ours:8.1f}")
    print(f"{'  baseline pure-Python loop (scaled from 4 rows)':52s} {loop:9.1f} "
          f"{loop / ours:8.0f}")
    print(f"{'F01 3280x3280 12-bit: lfcam unpack_12bit_be':52s} {ours12:9.3f}")
    print(f"target: Illum unpack <= 0.3 s -> {'met' if ours <= 0.3 else 'NOT met'}")


if __name__ == "__main__":
    main()
