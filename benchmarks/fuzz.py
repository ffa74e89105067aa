"""Fuzz campaign of lfcam's file loaders: mutated calibrations, profiles, PNG and TIFF headers.

Run from the repository root (one command, seeded, reproducible)::

    python benchmarks/fuzz.py                 # 10 000 cases, seed 0
    python benchmarks/fuzz.py --cases 300 --seed 1
    python benchmarks/fuzz.py --replay 1234   # rerun one case, show its traceback

Every case mutates one seed input (structurally: a parsed value replaced, removed or
retyped; or byte-wise: flips, truncation, splices, forged header fields) and calls the
library loaders in-process:

=============  =====================================================================
target         loaders
=============  =====================================================================
calib-compact  ``lfcam.calibrate.load_calibration`` (minimal form)
               (seed: ``data/synthetic/calib_system1.json``)
calib-full     the same (seed: ``benchmarks/fuzz_seeds/calib_white_system1_rect.json``,
               written by ``lfcam calibrate data/synthetic/white_system1_rect.png``)
profile        ``lfcam.camera.load_profile`` (seed: ``calibration/system1.toml``)
png            ``lfcam.io.load_capture``, ``lfcam.io.info.describe_file``
               (seed: a 64×48 16-bit grey PNG)
tiff           the same two (seed: a 64×48 16-bit grey TIFF, and a float32 one)
=============  =====================================================================

A case passes when every loader returns or raises an :class:`~lfcam.errors.LfcamError`
subclass, within :data:`MAX_SECONDS` and :data:`MAX_PEAK_MB` of peak resident memory
(Linux: the peak is reset through ``/proc/self/clear_refs`` before each case and read
from ``VmHWM`` after it, so native allocations by OpenCV or tifffile count). Anything else
is a finding: printed with the case number (``--replay N`` reruns it) and, with
``--save DIR``, the input is written there.
"""

from __future__ import annotations

import argparse
import copy
import io
import json
import math
import resource
import signal
import struct
import sys
import tempfile
import time
import traceback
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from lfcam.errors import LfcamError  # noqa: E402

MAX_SECONDS = 2.0
MAX_PEAK_MB = 500.0
HARD_TIMEOUT_S = 30  # a case still running after this is aborted (and is a finding)
ADDRESS_SPACE_LIMIT = 6 << 30  # a runaway allocation fails here instead of on the machine
SEEDS = {
    "calib-compact": ROOT / "data" / "synthetic" / "calib_system1.json",
    "calib-full": ROOT / "benchmarks" / "fuzz_seeds" / "calib_white_system1_rect.json",
    "profile": ROOT / "calibration" / "system1.toml",
}
# share of the cases per target (sums to 1)
MIX = {"calib-compact": 0.2, "calib-full": 0.2, "profile": 0.25, "png": 0.2, "tiff": 0.15}
WEIRD = [None, True, False, 0, -1, 1, 2**63, -(2**70), 1e308, -1e308, 1e-320, 0.5, -0.0,
         "", "x", "rect", "hex", "nan", "inf", [], [0], [1, 2], [[1, 2]], [None, None], {},
         {"a": 1}, [1e308, 1e308], [-1, -1], "\u00e9\u0000", 3.5, 100000, -100000]


# ----------------------------------------------------------------------------- memory / time

class _Peak:
    """Peak resident memory of this process per case (VmHWM, reset before each case)."""

    def __init__(self) -> None:
        self.ok = Path("/proc/self/clear_refs").exists()
        if self.ok:
            try:
                self.reset()
            except OSError:
                self.ok = False

    def reset(self) -> None:
        if self.ok:
            Path("/proc/self/clear_refs").write_text("5")

    def read_mb(self) -> float:
        if self.ok:
            for line in Path("/proc/self/status").read_text().splitlines():
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class _Timeout(BaseException):
    pass


def _alarm(signum, frame):  # noqa: ARG001
    raise _Timeout()


# ----------------------------------------------------------------------------- seed inputs

def _png_bytes(img: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def _tiff_bytes(img: np.ndarray) -> bytes:
    import tifffile

    bio = io.BytesIO()
    tifffile.imwrite(bio, img)
    return bio.getvalue()


def seed_inputs() -> dict[str, list[bytes]]:
    yy, xx = np.mgrid[0:48, 0:64]
    grey = (1000 + 300 * np.sin(xx / 3.0) * np.cos(yy / 4.0) + 20 * xx).astype(np.uint16)
    return {
        "calib-compact": [SEEDS["calib-compact"].read_bytes()],
        "calib-full": [SEEDS["calib-full"].read_bytes()],
        "profile": [SEEDS["profile"].read_bytes()],
        "png": [_png_bytes(grey), _png_bytes(grey.astype(np.uint8))],
        "tiff": [_tiff_bytes(grey), _tiff_bytes(grey.astype(np.float32) / 4096)],
    }


# ----------------------------------------------------------------------------- mutators

def _paths(node, prefix=()):
    """Every (path, value) in a parsed JSON/TOML tree (lists sampled, not exhausted)."""
    yield prefix, node
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        idx = range(len(node)) if len(node) <= 8 else (0, 1, len(node) // 2, len(node) - 1)
        for i in idx:
            yield from _paths(node[i], prefix + (i,))


def _weird(rng: np.random.Generator, old):
    r = rng.random()
    if r < 0.45:
        return copy.deepcopy(WEIRD[rng.integers(len(WEIRD))])
    if r < 0.6 and isinstance(old, (int, float)) and not isinstance(old, bool):
        return old * float(rng.choice([-1, 0, 1e-9, 1e9, 1e300]))
    if r < 0.7 and isinstance(old, list):
        return old[: rng.integers(0, max(1, len(old)))]
    if r < 0.8 and isinstance(old, list) and old:
        return old + old[: rng.integers(1, len(old) + 1)]
    if r < 0.9:
        depth = int(rng.integers(2, 200))
        return json.loads("[" * depth + "]" * depth)
    return float(rng.normal() * 10.0 ** int(rng.integers(-5, 6)))


def mutate_tree(rng: np.random.Generator, tree, n: int):
    tree = copy.deepcopy(tree)
    for _ in range(n):
        items = [(p, v) for p, v in _paths(tree) if p]
        if not items:
            return _weird(rng, tree)
        path, old = items[rng.integers(len(items))]
        parent = tree
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        op = rng.random()
        if op < 0.2 and isinstance(parent, dict):
            del parent[key]
        elif op < 0.3 and isinstance(parent, dict):
            parent[f"x{rng.integers(100)}"] = _weird(rng, None)
        else:
            parent[key] = _weird(rng, old)
    return tree


def mutate_bytes(rng: np.random.Generator, data: bytes, region: int | None = None) -> bytes:
    b = bytearray(data)
    span = len(b) if region is None else min(len(b), region)
    for _ in range(int(rng.integers(1, 6))):
        op = rng.random()
        pos = int(rng.integers(0, max(1, span)))
        if op < 0.35 and b:
            b[pos % len(b)] ^= 1 << int(rng.integers(8))
        elif op < 0.55 and b:
            b[pos % len(b)] = int(rng.choice([0, 0xFF, 0x7F, 0x80, ord("["), ord("{"), ord('"')]))
        elif op < 0.7:
            b[pos:pos] = bytes(rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8))
        elif op < 0.8:
            del b[pos:pos + int(rng.integers(1, 64))]
        elif op < 0.9:
            b = b[: int(rng.integers(0, len(b) + 1))]
        else:
            b[pos:pos] = rng.choice([b"NaN", b"Infinity", b"-1e999", b"[" * 5000, b"\xff\xfe",
                                     b'"\\ud800"', b"1" * 400])
    return bytes(b)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return '"null"'
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else
                                                  ("inf" if v > 0 else "-inf"))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}"
                               for k, x in v.items()) + "}"
    return json.dumps(str(v))


def to_toml(d: dict) -> str:
    lines = [f"{json.dumps(str(k))} = {_toml_value(v)}" for k, v in d.items()
             if not isinstance(v, dict)]
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"\n[{json.dumps(str(k))}]")
            lines += [f"{json.dumps(str(k2))} = {_toml_value(x)}" for k2, x in v.items()]
    return "\n".join(lines) + "\n"


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def mutate_png(rng: np.random.Generator, data: bytes) -> bytes:
    if rng.random() < 0.5:  # forged IHDR fields, CRC recomputed (so decoders believe it)
        w, h, depth, ctype, comp, filt, inter = struct.unpack(">IIBBBBB", data[16:29])
        choice = rng.integers(6)
        big = [0, 1, 2, 63, 65, 4096, 30000, 60000, 2**31 - 1, 2**32 - 1]
        if choice == 0:
            w = int(rng.choice(big))
        elif choice == 1:
            h = int(rng.choice(big))
        elif choice == 2:
            w, h = int(rng.choice(big)), int(rng.choice(big))
        elif choice == 3:
            depth = int(rng.choice([0, 1, 2, 4, 8, 16, 32, 255]))
        elif choice == 4:
            ctype = int(rng.choice([0, 1, 2, 3, 4, 5, 6, 7, 255]))
        else:
            inter = int(rng.integers(0, 3))
        ihdr = struct.pack(">IIBBBBB", w & 0xFFFFFFFF, h & 0xFFFFFFFF, depth, ctype, comp, filt,
                           inter)
        out = data[:8] + _png_chunk(b"IHDR", ihdr) + data[33:]
        return out if rng.random() < 0.8 else mutate_bytes(rng, out, 64)
    return mutate_bytes(rng, data, 96 if rng.random() < 0.7 else None)


def mutate_tiff(rng: np.random.Generator, data: bytes) -> bytes:
    b = bytearray(data)
    if rng.random() < 0.5:  # rewrite the value of one IFD entry (classic little-endian TIFF)
        ifd = struct.unpack("<I", b[4:8])[0]
        if 0 < ifd < len(b) - 2:
            n = struct.unpack("<H", b[ifd:ifd + 2])[0]
            if 0 < n < 100:
                e = ifd + 2 + 12 * int(rng.integers(n))
                if e + 12 <= len(b):
                    val = int(rng.choice([0, 1, 2, 3, 48, 64, 65535, 2**16 + 1, 30000, 2**31 - 1,
                                          2**32 - 1, len(b), len(b) * 8]))
                    typ = struct.unpack("<H", b[e + 2:e + 4])[0]
                    if typ == 3 and rng.random() < 0.7:
                        b[e + 8:e + 10] = struct.pack("<H", val & 0xFFFF)
                    else:
                        b[e + 8:e + 12] = struct.pack("<I", val & 0xFFFFFFFF)
                    if rng.random() < 0.2:
                        b[e + 4:e + 8] = struct.pack("<I", int(rng.choice([0, 2, 1 << 30])))
        return bytes(b)
    return mutate_bytes(rng, bytes(b), 400 if rng.random() < 0.7 else None)


# ----------------------------------------------------------------------------- loaders

def _loaders() -> dict[str, list[tuple[str, Callable[[Path], object]]]]:
    import lfcam.calibrate as cal
    from lfcam.camera import load_profile
    from lfcam.io import load_capture
    from lfcam.io.info import describe_file

    calib = [("calibrate.load_calibration", cal.load_calibration)]
    raster = [("io.load_capture", load_capture), ("io.info.describe_file", describe_file)]
    return {"calib-compact": calib, "calib-full": calib,
            "profile": [("camera.load_profile", load_profile)], "png": raster, "tiff": raster}


SUFFIX = {"calib-compact": ".json", "calib-full": ".json", "profile": ".toml", "png": ".png",
          "tiff": ".tiff"}


def make_case(seed: int, index: int, seeds: dict[str, list[bytes]]) -> tuple[str, bytes]:
    rng = np.random.default_rng([seed, index])
    targets = list(MIX)
    target = targets[int(rng.choice(len(targets), p=[MIX[t] for t in targets]))]
    base = seeds[target][int(rng.integers(len(seeds[target])))]
    if target.startswith("calib"):
        if rng.random() < 0.6:
            tree = mutate_tree(rng, json.loads(base), int(rng.integers(1, 4)))
            data = json.dumps(tree).encode()
        else:
            data = mutate_bytes(rng, base)
    elif target == "profile":
        import tomllib

        if rng.random() < 0.6:
            tree = mutate_tree(rng, tomllib.loads(base.decode()), int(rng.integers(1, 4)))
            data = to_toml(tree if isinstance(tree, dict) else {"x": tree}).encode()
        else:
            data = mutate_bytes(rng, base)
    elif target == "png":
        data = mutate_png(rng, base)
    else:
        data = mutate_tiff(rng, base)
    return target, data


@dataclass
class Stats:
    cases: int = 0
    accepted: int = 0  # every loader returned
    refused: int = 0  # at least one loader raised an LfcamError
    findings: int = 0
    max_s: float = 0.0
    max_mb: float = 0.0
    errors: dict = field(default_factory=dict)  # LfcamError class name → count


def innermost_lfcam_frame(tb_text: str) -> str:
    """``lfcam/...py:LINE`` of the deepest lfcam frame of a formatted traceback."""
    where = "?"
    for line in tb_text.splitlines():
        line = line.strip()
        if line.startswith('File "') and "/lfcam/" in line and "/benchmarks/" not in line:
            path = line.split('"')[1]
            lineno = line.split("line ")[1].split(",")[0] if "line " in line else "?"
            where = "lfcam/" + path.split("/lfcam/", 1)[1] + ":" + lineno
    return where


def run_case(path: Path, loaders, peak: _Peak) -> tuple[list, float, float, bool]:
    """Run every loader on ``path``; returns (problems, seconds, peak MB, all accepted)."""
    problems, accepted = [], True
    peak.reset()
    t0 = time.perf_counter()
    for name, fn in loaders:
        signal.alarm(HARD_TIMEOUT_S)
        try:
            fn(path)
        except LfcamError as exc:
            accepted = False
            problems.append((name, type(exc).__name__, None))
        except _Timeout:
            accepted = False
            problems.append((name, "Timeout", f"still running after {HARD_TIMEOUT_S} s"))
        except Exception as exc:  # noqa: BLE001 - exactly what the campaign looks for
            accepted = False
            problems.append((name, type(exc).__name__, traceback.format_exc()))
        finally:
            signal.alarm(0)
    return problems, time.perf_counter() - t0, peak.read_mb(), accepted


def campaign(seed: int = 0, cases: int = 10_000, save: Path | None = None,
             verbose: bool = True, first: int = 0) -> tuple[dict[str, Stats], list[dict]]:
    """Run ``cases`` cases; returns per-target stats and the findings."""
    import logging
    import warnings

    warnings.simplefilter("ignore")
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)  # it logs every damaged tag
    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        if hard == resource.RLIM_INFINITY or hard > ADDRESS_SPACE_LIMIT:
            resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE_LIMIT, hard))
    except (ValueError, OSError):
        pass
    old_handler = signal.signal(signal.SIGALRM, _alarm)
    seeds = seed_inputs()
    loaders = _loaders()
    peak = _Peak()
    stats = {t: Stats() for t in MIX}
    findings: list[dict] = []
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="lfcam-fuzz-") as tmp:
        for i in range(first, first + cases):
            target, data = make_case(seed, i, seeds)
            path = Path(tmp) / f"case{SUFFIX[target]}"
            path.write_bytes(data)
            problems, dt, mb, accepted = run_case(path, loaders[target], peak)
            st = stats[target]
            st.cases += 1
            st.max_s, st.max_mb = max(st.max_s, dt), max(st.max_mb, mb)
            bad = [p for p in problems if p[2] is not None]
            if accepted:
                st.accepted += 1
            elif not bad:
                st.refused += 1
            for _, cls, tb in problems:
                if tb is None:
                    st.errors[cls] = st.errors.get(cls, 0) + 1
            why = []
            if bad:
                why += [f"{name}: {cls}" for name, cls, _ in bad]
            if dt > MAX_SECONDS:
                why.append(f"{dt:.2f} s > {MAX_SECONDS} s")
            if mb > MAX_PEAK_MB:
                why.append(f"peak {mb:.0f} MB > {MAX_PEAK_MB:.0f} MB")
            if why:
                st.findings += 1
                wheres = [innermost_lfcam_frame(tb) for _, _, tb in bad if tb]
                f = {"case": i, "target": target, "why": why, "seconds": dt, "peak_mb": mb,
                     "tracebacks": [tb for _, _, tb in bad], "where": wheres}
                findings.append(f)
                if save is not None:
                    save.mkdir(parents=True, exist_ok=True)
                    (save / f"case{i}{SUFFIX[target]}").write_bytes(data)
                if verbose:
                    print(f"FINDING case {i} ({target}): {'; '.join(why)}", file=sys.stderr)
            if verbose and (i - first + 1) % 1000 == 0:
                print(f"  {i - first + 1}/{cases} cases, {time.perf_counter() - t_start:.0f} s",
                      file=sys.stderr)
    signal.signal(signal.SIGALRM, old_handler)
    return stats, findings


def table(stats: dict[str, Stats]) -> str:
    head = (f"{'target':<14} {'cases':>6} {'accepted':>8} {'refused':>8} {'findings':>8} "
            f"{'max s':>7} {'max MB':>7}  LfcamError subclasses raised")
    lines = [head, "-" * len(head)]
    tot = Stats()
    for t, s in stats.items():
        errs = ", ".join(f"{k} {v}" for k, v in sorted(s.errors.items(), key=lambda kv: -kv[1]))
        lines.append(f"{t:<14} {s.cases:>6} {s.accepted:>8} {s.refused:>8} {s.findings:>8} "
                     f"{s.max_s:>7.3f} {s.max_mb:>7.0f}  {errs}")
        tot.cases += s.cases
        tot.accepted += s.accepted
        tot.refused += s.refused
        tot.findings += s.findings
        tot.max_s, tot.max_mb = max(tot.max_s, s.max_s), max(tot.max_mb, s.max_mb)
    lines.append(f"{'total':<14} {tot.cases:>6} {tot.accepted:>8} {tot.refused:>8} "
                 f"{tot.findings:>8} {tot.max_s:>7.3f} {tot.max_mb:>7.0f}")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description="Fuzz lfcam's loaders (see the module docstring).")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cases", type=int, default=10_000)
    ap.add_argument("--save", type=Path, help="write the input of every finding here")
    ap.add_argument("--replay", type=int, metavar="N", help="rerun case N, print tracebacks")
    args = ap.parse_args()
    if args.replay is not None:
        stats, findings = campaign(args.seed, 1, args.save, verbose=False, first=args.replay)
        target = next(t for t, s in stats.items() if s.cases)
        print(f"case {args.replay} ({target}): {stats[target]}")
        for f in findings:
            print("\n".join(f["why"]))
            for tb in f["tracebacks"]:
                print(tb)
        return 1 if findings else 0
    t0 = time.perf_counter()
    stats, findings = campaign(args.seed, args.cases, args.save)
    print(f"lfcam fuzz: seed {args.seed}, {args.cases} cases in {time.perf_counter() - t0:.0f} s; "
          f"limits {MAX_SECONDS} s and {MAX_PEAK_MB:.0f} MB a case")
    print(table(stats))
    if findings:
        print(f"\n{len(findings)} finding(s):")
        for f in findings:
            where = ", ".join(f["where"]) or "-"
            print(f"  case {f['case']} ({f['target']}): {'; '.join(f['why'])} at {where}")
            for tb in f["tracebacks"]:
                if tb:
                    print("    " + tb.strip().splitlines()[-1])
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main())
