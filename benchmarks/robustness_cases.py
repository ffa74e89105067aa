"""Reproduce every case of docs/robustness.md and print one Markdown table row per case.

Run: ``python benchmarks/robustness_cases.py [--only ID ...]`` from the repository root.
Each case runs ``python -m lfcam ...`` in a child process (the checkout's own code), with
its inputs in a scratch folder, and records the exit status, the last line of stderr, the
wall time, the child's peak RSS and whether any input file changed (sha256 before/after).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SYN = ROOT / "data" / "synthetic"
sys.path.insert(0, str(ROOT))


def sha(path: Path) -> str | None:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None


def png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png_header_only(path: Path, width: int, height: int, bit_depth: int = 8) -> None:
    """A PNG whose IHDR claims ``width × height`` grey pixels, with one tiny IDAT."""
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, 0, 0, 0, 0)
    idat = zlib.compress(b"\0" * 64)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", idat)
                     + png_chunk(b"IEND", b""))


def png_bomb(path: Path, side: int) -> None:
    """A valid 16-bit grey PNG of ``side``² zero pixels (compresses ~1000:1)."""
    comp = zlib.compressobj(9)
    row = b"\0" * (1 + 2 * side)
    parts = [comp.compress(row) for _ in range(side)]
    parts.append(comp.flush())
    ihdr = struct.pack(">IIBBBBB", side, side, 16, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr)
                     + png_chunk(b"IDAT", b"".join(parts)) + png_chunk(b"IEND", b""))


def sha1_mismatch_lfp(path: Path) -> None:
    sys.path.insert(0, str(ROOT / "tests" / "io"))
    from io_testlib import small_frame_meta

    from lfcam.io import read_lfp, write_lfp

    raw = (np.arange(64 * 48) % 4000).astype(np.uint16).reshape(48, 64)
    write_lfp(path, raw, small_frame_meta(64, 48))
    c = read_lfp(path)
    data = bytearray(path.read_bytes())
    data[c.sections[-1].offset] ^= 1
    path.write_bytes(bytes(data))


def build(tmp: Path) -> None:
    """Scratch inputs of every case."""
    shutil.copy(SYN / "point_system1_1100mm_dh0.png", tmp / "cap.png")
    shutil.copy(SYN / "point_system1_1100mm_dh0.profile.toml", tmp / "cap.profile.toml")
    shutil.copy(SYN / "calib_system1.json", tmp / "calib.json")
    os.link(tmp / "cap.png", tmp / "hard.png")
    (tmp / "sym.png").symlink_to(tmp / "cap.png")
    (tmp / "c.csv").write_text("y1_mm,y2_mm\n0.1,-0.1\n0.2,-0.05\n")
    scene = {"seed": 1, "rays_per_source": 20000,
             "objects": [{"type": "point", "distance_mm": 1000.0}]}
    (tmp / "x.truth.json").write_text(json.dumps(scene))
    (tmp / "scene.json").write_text(json.dumps(scene))
    prof = (ROOT / "calibration" / "system1.toml").read_text()
    (tmp / "y.profile.toml").write_text("# my notes: keep me\n" + prof)
    (tmp / "nan_scene.json").write_text(
        '{"objects": [{"type": "point", "distance_mm": NaN}]}')
    many = {"objects": [{"type": "point", "distance_mm": 1000.0, "rays": 500_000_000}] * 2000}
    (tmp / "many.json").write_text(json.dumps(many))
    (tmp / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    png_header_only(tmp / "huge_header.png", 60000, 60000)
    png_bomb(tmp / "bomb.png", 30000)
    (tmp / "bad.toml").write_text(prof.replace("pitch_mm = 1.34", "pitch_mm = -1.34"))
    sha1_mismatch_lfp(tmp / "bad.lfp")
    import cv2

    cv2.imwrite(str(tmp / "sat.png"), np.full((1024, 1024), 65535, np.uint16))
    # issue 18, second part: a white with heavy Monte-Carlo noise (1 sample per boundary
    # pixel), 640² crop and full sensor, of system 2
    from lfcam.camera import load_profile
    from lfcam.sim.capture import simulate, write_capture
    from lfcam.sim.scene import scene_from_dict

    for name, size in (("badwhite.png", 640), ("badwhite_full.png", None)):
        scene = {"seed": 3, "samples_per_pixel": 1, "objects": [{"type": "white"}]}
        if size:
            scene["camera"] = {"sensor": {"width_px": size, "height_px": size}}
        raw, used, truth = simulate(load_profile("system2"), scene_from_dict(scene))
        write_capture(tmp / name, raw, used, truth)
    d = json.loads((SYN / "calib_system2.json").read_text())
    d["quality"] = {"verdict": "poor", "accepted_poor": False, "reasons": [
        "coverage 0.323 (2016 of 6241 fully visible lenses measured; limit 0.9)"]}
    (tmp / "poor.json").write_text(json.dumps(d))
    shutil.copy(SYN / "point_system2_300mm_dh0.png", tmp / "cap2.png")
    shutil.copy(SYN / "point_system2_300mm_dh0.profile.toml", tmp / "cap2.profile.toml")
    shutil.copy(SYN / "calib_system2.json", tmp / "calib2.json")
    (tmp / "pitch1000.toml").write_text(
        (tmp / "cap.profile.toml").read_text().replace("pitch_mm = 1.34", "pitch_mm = 1000",
                                                       1))
    (tmp / "in").mkdir()
    shutil.copy(tmp / "cap.png", tmp / "in" / "cap.png")
    shutil.copy(tmp / "cap.profile.toml", tmp / "in" / "cap.profile.toml")
    (tmp / "in" / "gone.png").symlink_to(tmp / "nowhere.png")


D = ["--calibration", "calib.json", "--profile", "cap.profile.toml"]
CASES: list[tuple[str, list[str], list[str]]] = [
    # id, argv (after `python -m lfcam`), inputs whose bytes must not change
    ("1a refocus -o = capture", ["refocus", "cap.png", *D, "--shift", "0", "-o", "cap.png"],
     ["cap.png"]),
    ("1b refocus -o = hard link", ["refocus", "cap.png", *D, "--shift", "0", "-o", "hard.png"],
     ["cap.png"]),
    ("1c refocus -o = symlink", ["refocus", "cap.png", *D, "--shift", "0", "-o", "sym.png"],
     ["cap.png"]),
    ("1d optics inverse in = out", ["optics", "inverse", "--profile", "system1", "--model",
                                    "exact", "--input", "c.csv", "--output", "c.csv"], ["c.csv"]),
    ("1e simulate scene = truth", ["simulate", "--profile", "system1", "--scene", "x.truth.json",
                                   "-o", "x.png"], ["x.truth.json"]),
    ("1f simulate profile = sidecar", ["simulate", "--profile", "y.profile.toml", "--scene",
                                       "scene.json", "-o", "y.png"], ["y.profile.toml"]),
    ("1g distance -o unwritable", ["distance", "cap.png", *D, "-o", "/proc/lfcam-out"],
     ["cap.png"]),
    ("2a PNG header 60000²", ["info", "huge_header.png"], []),
    ("2b 16-bit PNG 30000² (1.7 MB)", ["info", "bomb.png"], []),
    ("3 calibration JSON depth 1e5", ["distance", "cap.png", "--calibration", "deep.json",
                                      "--profile", "cap.profile.toml", "-o", "out3"], []),
    ("4a simulate 2000 × 5e8 rays", ["simulate", "--profile", "system1", "--scene", "many.json",
                                     "-o", "many.png"], []),
    ("4b scene distance NaN", ["simulate", "--profile", "system1", "--scene", "nan_scene.json",
                               "-o", "nan.png"], []),
    ("5a --y1 -1e-12", ["optics", "inverse", "--profile", "system1", "--model", "exact",
                        "--y1", "-1e-12", "--y2", "0.01"], []),
    ("5b --tolerance nan", ["distance", "cap.png", *D, "--tolerance", "nan", "--fast",
                            "-o", "out5b"], []),
    ("5c --tolerance -5", ["distance", "cap.png", *D, "--tolerance", "-5", "--fast",
                           "-o", "out5c"], []),
    ("5d refocus --d-in=-5", ["refocus", "cap.png", *D, "--distance", "1000", "--d-in=-5",
                              "-o", "r5d.png"], []),
    ("5e distance on sha1 mismatch", ["distance", "bad.lfp", "--calibration", "calib.json",
                                      "--profile", "system1", "-o", "out5e"], []),
    ("5f bad profile value", ["optics", "forward", "--profile", "bad.toml", "--distance",
                              "1000"], []),
    ("5g calibrate --help", ["calibrate", "--help"], []),
    ("7 all-saturated frame", ["distance", "sat.png", *D, "--fast", "-o", "out7"], []),
    ("8a calibrate a bad white", ["calibrate", "badwhite.png", "-o", "bad.json"],
     ["badwhite.png"]),
    ("8b calibrate --accept-poor", ["calibrate", "badwhite_full.png", "--accept-poor", "-o",
                                    "badfull.json"], ["badwhite_full.png"]),
    ("8c distance, poor calibration", ["distance", "cap2.png", "--calibration", "poor.json",
                                       "--fast", "-o", "out8c"], ["cap2.png", "poor.json"]),
    ("8d decode, poor calibration", ["decode", "cap2.png", "--calibration", "poor.json", "-o",
                                     "lf8d"], ["cap2.png", "poor.json"]),
    ("8e refocus, poor calibration", ["refocus", "cap2.png", "--calibration", "poor.json",
                                      "--shift", "0", "-o", "r8e.png"], ["cap2.png"]),
    ("8f batch, poor calibration", ["batch", "in", "--calibration", "poor.json", "-o",
                                    "out8f", "--fast", "--workers", "1"], ["poor.json"]),
    ("9 one source, accepted poor calibration", ["distance", "cap2.png", "--calibration",
                                                 "badfull.json", "--fast", "-o", "out9"],
     ["cap2.png"]),
    ("10 profile mla.pitch_mm = 1000", ["distance", "cap.png", "--calibration", "calib.json",
                                        "--profile", "pitch1000.toml", "-o", "out10"],
     ["cap.png"]),
    ("11 guide: 512² calibration, 1024² capture", ["distance", "cap.png", "--calibration",
                                                   "guide.json", "-o", "out11"], ["cap.png"]),
    ("12 batch: dangling symlink", ["batch", "in", "--calibration", "calib.json", "-o",
                                    "out12", "--fast", "--workers", "1"], []),
]


WRAP = ("import atexit, resource, runpy, sys\n"
        "atexit.register(lambda: sys.stderr.write("
        "f'@@RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}\\n'))\n"
        "sys.argv = ['lfcam', *sys.argv[1:]]\n"
        "runpy.run_module('lfcam', run_name='__main__')\n")


def run_case(tmp: Path, argv: list[str], timeout: float):
    """(status, last stderr line, seconds, peak RSS MB or None, first stdout line)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", WRAP, *argv], cwd=tmp, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        return f"still running after {timeout:.0f} s (killed)", "", timeout, None, ""
    dt = time.perf_counter() - t0
    rss = None
    lines = []
    for ln in err.decode(errors="replace").splitlines():
        if ln.startswith("@@RSS "):
            rss = int(ln.split()[1]) / 1024
        elif ln.strip():
            lines.append(ln)
    if any(ln.startswith("Traceback") for ln in lines):
        last = "TRACEBACK: " + lines[-1]
    else:
        last = " / ".join(lines[-2:]) if lines else ""
    so = out.decode(errors="replace").strip().splitlines()
    return f"exit {proc.returncode}", last[:220], dt, rss, (so[0][:150] if so else "")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="case id prefixes to run")
    ap.add_argument("--timeout", type=float, default=60.0)
    args = ap.parse_args()
    base = Path(tempfile.mkdtemp(prefix="lfcam-robust-"))
    pristine, tmp = base / "pristine", base / "run"
    try:
        pristine.mkdir()
        build(pristine)
        shutil.copytree(pristine, tmp, symlinks=False, ignore_dangling_symlinks=True)
        (tmp / "in" / "gone.png").symlink_to(tmp / "nowhere.png")
        os.unlink(tmp / "hard.png")
        os.link(tmp / "cap.png", tmp / "hard.png")
        os.unlink(tmp / "sym.png")
        (tmp / "sym.png").symlink_to(tmp / "cap.png")
        print("| case | command | result | stderr (last line) / stdout | s | peak RSS MB "
              "| inputs |")
        print("|---|---|---|---|---|---|---|")
        for cid, argv, inputs in CASES:
            if args.only and not any(cid.startswith(o) for o in args.only):
                continue
            before = {f: sha(tmp / f) for f in inputs}
            t = 15.0 if cid.startswith("4a") else 600.0 if cid.startswith("9") else \
                args.timeout
            if cid.startswith("11") and not (tmp / "guide.json").exists():
                run_case(tmp, ["calibrate", str(SYN / "white_system1_rect.png"), "-o",
                               "guide.json"], args.timeout)
            code, last, dt, rss, so = run_case(tmp, argv, t)
            changed = [f for f in inputs if sha(tmp / f) != before[f]]
            inp = ("CHANGED: " + ", ".join(changed)) if changed else ("unchanged" if inputs
                                                                      else "—")
            if not last and so:
                last = "stdout: " + so
            mem = "—" if rss is None else f"{rss:.0f}"
            print(f"| {cid} | `lfcam {' '.join(argv)}` | {code} | {last.replace('|', '/')} | "
                  f"{dt:.1f} | {mem} | {inp} |", flush=True)
            for f in changed:  # restore what a case destroyed, for the next cases
                (tmp / f).unlink()
                shutil.copy(pristine / f, tmp / f)
    finally:
        shutil.rmtree(base, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
