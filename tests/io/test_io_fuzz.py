"""Fuzz: mutated real and synthetic containers raise only documented LfcamError subclasses.

Bounded for CI (a few seconds). Longer run:
``LFCAM_FUZZ_EXAMPLES=5000 python -m pytest -q tests/io/test_io_fuzz.py``.
"""

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from io_testlib import REALDATA, small_frame_meta

from lfcam.errors import (
    ChecksumError,
    ContainerError,
    InputFileError,
    MetadataError,
    NoRawFrameError,
    RawDataError,
    TruncatedFileError,
    UnsupportedFormatError,
)
from lfcam.io import load_capture, write_lfp
from lfcam.io.info import describe_file

DOCUMENTED = (ChecksumError, ContainerError, MetadataError, NoRawFrameError, RawDataError,
              TruncatedFileError, UnsupportedFormatError, InputFileError)
N = int(os.environ.get("LFCAM_FUZZ_EXAMPLES", "40"))
_TMP = Path(tempfile.mkdtemp(prefix="lfcam-fuzz-"))


def _seeds() -> list[bytes]:
    out = []
    for packing, bits in (("12bit", 12), ("10bit", 10)):
        img = np.random.default_rng(bits).integers(0, 1 << bits, (4, 8), dtype=np.uint16)
        p = write_lfp(_TMP / f"seed{bits}.lfp", img, small_frame_meta(8, 4, packing),
                      packing=packing, white_image=img)
        out.append(p.read_bytes())
    for name in ("illum-demo.LFP", "IMG_0002-dm.lfp"):
        if (REALDATA / name).is_file():
            out.append((REALDATA / name).read_bytes())
    return out


SEEDS = _seeds()


@st.composite
def mutated(draw):
    data = bytearray(draw(st.sampled_from(SEEDS)))
    # bias positions to the structure-rich start (header, names, JSON) half of the time
    for _ in range(draw(st.integers(1, 4))):
        hot = draw(st.booleans())
        hi = min(len(data), 2000) if hot else len(data)
        if hi == 0:
            break
        pos = draw(st.integers(0, hi - 1))
        op = draw(st.sampled_from(["flip", "set32", "truncate", "insert", "delete"]))
        if op == "flip":
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "set32":
            data[pos : pos + 4] = draw(st.binary(min_size=4, max_size=4))
        elif op == "truncate":
            del data[pos:]
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        else:
            del data[pos : pos + draw(st.integers(1, 32))]
    return bytes(data), draw(st.sampled_from(["error", "off"]))


@settings(max_examples=N, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(mutated())
def test_mutated_containers_raise_only_documented_errors(case):
    data, verify = case
    p = _TMP / "case.lfp"
    p.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for fn in (lambda: describe_file(p, verify=verify),
                   lambda: load_capture(p, verify=verify)):
            try:
                fn()
            except DOCUMENTED:
                pass


@pytest.mark.parametrize("payload", [b"", b"\x89", b"\x89LFP\r\n\x1a\n", b"\x89LFP\r\n\x1a\n" +
                                     b"\0\0\0\1\0\0\0\0" + b"\x89LFM\r\n\x1a\n" + b"\0" * 7])
def test_tiny_prefixes(tmp_path, payload):
    p = tmp_path / "t.lfp"
    p.write_bytes(payload)
    with pytest.raises(DOCUMENTED):
        describe_file(p)
