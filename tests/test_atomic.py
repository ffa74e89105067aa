"""Atomic writes: complete or untouched, no temporary files left, ordinary permissions."""

from __future__ import annotations

import os
import stat

import pytest

from lfcam.atomic import atomic_copy, atomic_write, atomic_write_bytes, atomic_write_text


def test_replaces_whole_file_and_leaves_no_temp(tmp_path):
    target = tmp_path / "out.csv"
    target.write_text("old\n")
    atomic_write_text(target, "a,b\n1,2\n")
    assert target.read_text() == "a,b\n1,2\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]


def test_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "map.tiff"
    target.write_bytes(b"previous")

    def boom(tmp):
        tmp.write_bytes(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, boom)
    assert target.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["map.tiff"]


def test_chunks_suffix_and_permissions(tmp_path):
    seen = {}
    atomic_write(tmp_path / "x.png", lambda tmp: seen.setdefault("suffix", tmp.suffix) and
                 tmp.write_bytes(b""))
    assert seen["suffix"] == ".png"  # writers that pick the format by suffix still work
    out = atomic_write_bytes(tmp_path / "c.bin", [b"ab", b"cd"])
    assert out.read_bytes() == b"abcd"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~umask


def test_copy_has_ordinary_permissions_and_leaves_the_source(tmp_path):
    src = tmp_path / "a.csv"
    src.write_bytes(b"x,y\n1,2\n")
    os.chmod(src, 0o600)  # (a copy's mode is the umask's, not the source's)
    out = atomic_copy(src, tmp_path / "sub" / "b.csv")
    assert out.read_bytes() == src.read_bytes() == b"x,y\n1,2\n"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~umask
    assert stat.S_IMODE(src.stat().st_mode) == 0o600
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["b.csv"]
