"""File helpers: atomic output (every file lfcam writes appears complete or not at all) and
content hashes.

The content goes to a temporary file in the target's folder (same file system, same suffix so
format-sniffing writers such as tifffile and OpenCV still work, ordinary permissions after the
umask), which then replaces the target by one ``os.replace``. On any error the temporary file
is removed and the target is left as it was.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Run ``write(tmp_path)`` and move the result onto ``path`` atomically; returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    try:
        ordinary_permissions(tmp)
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def ordinary_permissions(path: str | Path) -> None:
    """Give a file or folder the permissions an ordinary ``open`` or ``mkdir`` would have
    (0o666 or 0o777 less the umask): :mod:`tempfile` makes them 0o600 and 0o700, which a
    rename onto the output name would keep."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, (0o777 if Path(path).is_dir() else 0o666) & ~umask)


def atomic_copy(src: str | Path, dst: str | Path) -> Path:
    """Copy the file ``src`` to ``dst`` atomically (bytes only; ordinary permissions)."""
    import shutil

    return atomic_write(dst, lambda tmp: shutil.copyfile(src, tmp))


def atomic_write_bytes(path: str | Path, data: bytes | Iterable[bytes]) -> Path:
    """Write bytes (or a sequence of byte chunks) to ``path`` atomically."""
    chunks = [data] if isinstance(data, (bytes, bytearray, memoryview)) else data

    def write(tmp: Path) -> None:
        with tmp.open("wb") as fh:
            for chunk in chunks:
                fh.write(chunk)

    return atomic_write(path, write)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write UTF-8 text to ``path`` atomically (newlines as given)."""
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8", newline=""))


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes, read in ``chunk``-byte blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def _same(a: Path, b: Path) -> bool:
    """Same file: equal resolved paths (symlinks followed), or one inode (hard links)."""
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # either does not exist (yet)
        return False


def refuse_overwrite(inputs: Iterable[str | Path | None],
                     outputs: Iterable[str | Path | None]) -> None:
    """Refuse to run when any output path names one of the inputs.

    Paths are compared resolved (``..``, symlinks) and, for existing files, with
    :func:`os.path.samefile`, so a hard link or a symlink to an input counts as the input.
    ``None`` entries are skipped. Call it before any heavy work.

    Raises
    ------
    OutputPathError
        One line naming the output and the input it would replace.
    """
    from lfcam.errors import OutputPathError

    ins = [Path(p) for p in inputs if p is not None]
    for out in outputs:
        if out is None:
            continue
        o = Path(out)
        for i in ins:
            if _same(o, i):
                raise OutputPathError(f"output {o} would overwrite input {i}; choose another "
                                      "output name")


def check_output_dir(folder: str | Path) -> None:
    """Fail early unless ``folder`` is, or can be created as, a directory lfcam can write.

    Tried for real (permission bits say nothing for root or read-only mounts): missing
    folders are created, a temporary file is made and removed, then the folders this call
    created are removed again, so nothing is left behind.

    Raises
    ------
    OutputPathError
        When the folder (or an ancestor) is a file, cannot be created, or is not writable.
    """
    from lfcam.errors import OutputPathError

    p = Path(folder)
    created: list[Path] = []
    probe = p
    while not probe.exists() and probe.parent != probe:
        created.append(probe)
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        what = "is" if probe == p else f"is inside {probe}, which is"
        raise OutputPathError(f"output folder {folder} {what} not a directory")
    try:
        for d in reversed(created):
            d.mkdir()
        fd, tmp = tempfile.mkstemp(dir=p, prefix=".lfcam-write-test.")
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise OutputPathError(f"output folder {folder} is not writable "
                              f"({exc.strerror or exc})") from None
    finally:
        for d in created:
            try:
                d.rmdir()
            except OSError:
                pass
