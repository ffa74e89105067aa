"""Deterministic generator of the synthetic capture set in this folder.

Run from the repository root: ``python data/synthetic/make.py`` (about 4 minutes on one core);
``python data/synthetic/make.py PREFIX ...`` renders only the captures whose names start with a
prefix (e.g. ``point_cooke_triplet``) and updates their entries in ``index.json``.
Every capture is ``NAME.png`` (16-bit raw), ``NAME.profile.toml`` and ``NAME.truth.json``;
``index.json`` lists them. Choices that keep the set small are explained in docs/simulate.md.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from lfcam.camera import load_profile  # noqa: E402
from lfcam.sim.capture import simulate, write_capture  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

DISTANCES_MM = [3500, 3250, 3000, 2800, 2500, 2200, 2000, 1800, 1500, 1300, 1100, 900, 750,
                600, 450, 300]  # the seed's Table 2 grid
OFFSETS_MM = [0, 5, 10]
SEED = 20240601


def captures() -> list[tuple[str, str, dict]]:
    """(name, profile, scene) for every capture, in a fixed order."""
    out = []
    for system, size in (("system1", 512), ("system2", 768)):
        for grid in ("rect", "hex"):
            out.append((f"white_{system}_{grid}", system, {
                "seed": SEED, "objects": [{"type": "white"}],
                "camera": {"mla": {"grid": grid}, "sensor": {"width_px": size,
                                                            "height_px": size}}}))
    for system in ("system1", "system2"):
        for dist in DISTANCES_MM:
            for off in OFFSETS_MM:
                out.append((f"point_{system}_{dist}mm_dh{off}", system, {
                    "seed": SEED + dist + off, "rays_per_source": 300_000,
                    "objects": [{"type": "point", "distance_mm": dist, "offset_mm": off}]}))
    for dist in DISTANCES_MM:
        out.append((f"line_system1_{dist}mm", "system1", {
            "seed": SEED + dist, "rays_per_source": 1_000_000,
            "objects": [{"type": "line", "distance_mm": dist, "start_mm": [0, 0],
                         "end_mm": [0, 10]}]}))
    # multi-element main lenses (calibration/cooke_triplet.toml, double_gauss.toml; focus 1 m):
    # a few point sources in front of and behind focus, off axis, and one line
    for lens, off in (("cooke_triplet", 2), ("double_gauss", 5)):
        for dist in (300, 1000, 3500):
            out.append((f"point_{lens}_{dist}mm_dh{off}", lens, {
                "seed": SEED + dist + off, "rays_per_source": 300_000,
                "objects": [{"type": "point", "distance_mm": dist, "offset_mm": off}]}))
    out.append(("line_double_gauss_1500mm", "double_gauss", {
        "seed": SEED + 1500, "rays_per_source": 1_000_000,
        "objects": [{"type": "line", "distance_mm": 1500, "start_mm": [0, 0],
                     "end_mm": [0, 10]}]}))
    out.append(("plane_system1_1500mm_checker", "system1", {
        "seed": SEED, "samples_per_pixel": 16, "interior_samples": 4,
        "objects": [{"type": "plane", "distance_mm": 1500, "texture": "checkerboard",
                     "square_mm": 20.0, "low": 0.2, "high": 1.0}],
        "camera": {"sensor": {"width_px": 512, "height_px": 512}}}))
    return out


def main() -> None:
    prefixes = sys.argv[1:]
    index_path = HERE / "index.json"
    index = []
    if prefixes:
        index = [e for e in json.loads(index_path.read_text(encoding="utf-8"))
                 if not e["name"].startswith(tuple(prefixes))]
    for name, system, body in captures():
        if prefixes and not name.startswith(tuple(prefixes)):
            continue
        raw, used, truth = simulate(load_profile(system), scene_from_dict(body))
        img, prof, tru = write_capture(HERE / f"{name}.png", raw, used, truth)
        index.append({"name": name, "profile": system, "scene": body,
                      "files": [img.name, prof.name, tru.name]})
        print(name, raw.shape, img.stat().st_size + tru.stat().st_size, flush=True)
    order = {name: k for k, (name, _, _) in enumerate(captures())}
    index.sort(key=lambda e: order.get(e["name"], len(order)))
    index_path.write_text(json.dumps(index, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
