"""What a run read of its dataset: page-cache eviction, resident pages, and the jobs' I/O lines.

Two measures, on a dataset evicted from the page cache before the run (:func:`evict`,
``posix_fadvise(DONTNEED)`` per file, no root needed):

* **read_bytes** of every job (``/proc/self/io``, logged by
  :func:`pipeline25d.core.logsetup.log_job_resources`, children such as ``osgconv`` included),
  summed: the bytes that had to come from storage. With the dataset evicted and everything
  else the jobs read already cached (code, their own fresh temporary files), that is the dataset
  bytes read, each at most once per run (later reads of a page are cache hits), plus read-ahead.
  ``rchar`` is not used for this: it counts every byte read() returned, the job's own .osgt,
  OBJ and PNG conversions and its imports included, several times the dataset bytes; it is
  reported beside as the upper bound of all reading.
* **resident** bytes of the dataset after the run (``mincore`` over each file): an independent
  count of the dataset pages the run brought in, per level.
"""

from __future__ import annotations

import ctypes
import mmap
import os
from collections.abc import Iterable
from pathlib import Path

from pipeline25d.core.logsetup import RESOURCE_KEYS, job_logs, job_record, read_job_record


def dataset_files(folder: Path) -> list[Path]:
    return sorted(Path(d) / n for d, _, names in os.walk(folder) for n in names)


def evict(folder: Path) -> int:
    """Drop ``folder``'s files from the page cache (written back first); return their bytes."""
    os.sync()
    total = 0
    for path in dataset_files(folder):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            total += os.fstat(fd).st_size
        finally:
            os.close(fd)
    return total


def _libc():
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long]
    libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    return libc


def resident_bytes(path: Path, libc=None) -> int:
    """Bytes of ``path`` in the page cache now (whole pages, capped at the file's size)."""
    libc = libc or _libc()
    size = path.stat().st_size
    if size == 0:
        return 0
    fd = os.open(path, os.O_RDONLY)
    try:
        addr = libc.mmap(None, size, mmap.PROT_READ, mmap.MAP_SHARED, fd, 0)
        if addr in (None, ctypes.c_void_p(-1).value):
            raise OSError(ctypes.get_errno(), f"mmap of {path} failed")
        pages = (size + mmap.PAGESIZE - 1) // mmap.PAGESIZE
        vec = (ctypes.c_ubyte * pages)()
        try:
            if libc.mincore(addr, size, vec) != 0:
                raise OSError(ctypes.get_errno(), f"mincore of {path} failed")
        finally:
            libc.munmap(addr, size)
    finally:
        os.close(fd)
    return min(size, sum(b & 1 for b in bytes(vec)) * mmap.PAGESIZE)


def resident(folder: Path, level_of=None) -> dict:
    """{"bytes": resident bytes under ``folder``, "by_level": {level: bytes}}; ``level_of(path)``
    names a file's level."""
    libc, total, by_level = _libc(), 0, {}
    for path in dataset_files(folder):
        b = resident_bytes(path, libc)
        total += b
        if level_of is not None and b:
            key = str(level_of(path))
            by_level[key] = by_level.get(key, 0) + b
    return {"bytes": total, "by_level": dict(sorted(by_level.items()))}


def job_resources(lines: Iterable[str]) -> dict | None:
    """The last resources line of a job log as a dict, or None."""
    return _resources(job_record(lines))


def _resources(rec: dict) -> dict | None:
    """The resources of a :func:`~pipeline25d.core.logsetup.job_record`, or None without that line."""
    return {k: rec[k] for k in RESOURCE_KEYS} if RESOURCE_KEYS[0] in rec else None


def stage_resources(logs: Path) -> dict[str, dict]:
    """Per stage (:func:`pipeline25d.core.logsetup.job_logs`): jobs with a resources line, summed rchar and
    read_bytes, and the largest peak RSS of a job and of a job's child, MB."""
    out: dict[str, dict] = {}
    for stage, log in job_logs(logs):
        rec = _resources(read_job_record(log))
        if rec is None:
            continue
        s = out.setdefault(stage, {"jobs": 0, "rchar": 0, "read_bytes": 0, "peak_rss_mb": 0.0,
                                   "child_peak_rss_mb": 0.0})
        s["jobs"] += 1
        s["rchar"] += rec["rchar"]
        s["read_bytes"] += rec["read_bytes"]
        s["peak_rss_mb"] = max(s["peak_rss_mb"], round(rec["max_rss_kb"] / 1024, 1))
        s["child_peak_rss_mb"] = max(s["child_peak_rss_mb"], round(rec["children_max_rss_kb"] / 1024, 1))
    return out
