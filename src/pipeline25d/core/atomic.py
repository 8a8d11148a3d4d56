"""Atomic file output: write to a temporary name in the target folder, then rename.

An interrupted job therefore never leaves a file that looks complete.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from pipeline25d.core.errors import OutputError
from pipeline25d.core.stopping import end_if_stopped

FULL_BYTES = 1 << 20   # a device with less free space than this when a write fails is taken as full


@contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    ``suffix`` defaults to the target's suffix so tools that pick a driver by file
    extension (GDAL) still do so. On error the temporary file or folder is removed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
                               dir=path.parent)
    os.close(fd)
    os.unlink(tmp)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        end_if_stopped()               # a stop signal whose exception a library dropped: not a finished output
        os.replace(tmp_path, path)
    except BaseException as exc:
        full = isinstance(exc, (OSError, RuntimeError)) and device_full(path.parent, exc)
        if tmp_path.is_dir():
            shutil.rmtree(tmp_path, ignore_errors=True)
        elif tmp_path.exists():
            tmp_path.unlink()
        if full and not isinstance(exc, OutputError):
            raise OutputError(path, f"No space left on device ({exc})") from exc
        raise


def device_full(folder: Path, exc: BaseException | None = None) -> bool:
    """Whether a failed write into ``folder`` failed for want of space: ENOSPC, or (GDAL, which
    does not say) less than :data:`FULL_BYTES` free there while the failed output still lies on it."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    try:
        stat = os.statvfs(folder)
    except OSError:
        return False
    return stat.f_bavail * stat.f_frsize < FULL_BYTES


def write_json(path: str | Path, data: Any, indent: int | None = 1) -> None:
    """Write ``data`` as JSON atomically, indented unless ``indent`` is None (for big files:
    the indenting encoder is pure Python, ~100x slower than the compact one)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=indent, sort_keys=False) + "\n")


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def replace_dir(src: Path, dst: Path) -> None:
    """Move a finished folder onto ``dst``, replacing an older one (not after a stop signal)."""
    end_if_stopped()
    dst = Path(dst)
    if dst.exists():
        old = dst.with_name(f".{dst.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(dst, old)
        os.replace(src, dst)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(src, dst)
