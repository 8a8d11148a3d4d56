"""An OBJ's lines a block at a time, and their words, cut on a block's bytes at once.

What :mod:`pipeline25d.formats.obj_slabs` reads a large OBJ with: each line's kind by its keyword
(:func:`kinds`), a block's lines tidied as a whole read's text (tabs, indented lines, a byte order
mark, CRs alone as line ends: :func:`~pipeline25d.formats.meshfile.tidied_obj_text`), and the words
of v, vt and f lines found on the lines' bytes at once (:class:`Words`), not line by line in Python.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path

import numpy as np

#: bytes of lines read at a time
READ_BYTES = 8 * 2 ** 20


#: line kinds: a vertex, a texture coordinate, a face, anything else
V, VT, F, OTHER = 1, 2, 3, 0


def kinds(lines: list[bytes]) -> np.ndarray:
    """Each line's kind (:data:`V`, :data:`VT`, :data:`F`, :data:`OTHER`) by its keyword: both passes
    count the v and vt lines alike, so an index names the same row in each."""
    heads = np.array(lines, dtype="S3")         # each line's first three bytes
    two = heads.astype("S2")
    kind = np.full(len(lines), OTHER, dtype=np.int8)
    kind[(two == b"v ") | (two == b"v\t")] = V
    kind[(two == b"f ") | (two == b"f\t")] = F
    kind[(heads == b"vt ") | (heads == b"vt\t")] = VT
    return kind


def line_blocks(path: Path) -> Iterator[list[bytes]]:
    """The file's lines a block at a time, tidied as a whole read's where the file needs it
    (:func:`~.meshfile.tidied_obj_text`: tabs, indented lines, a byte order mark, CRs alone)."""
    from pipeline25d.formats.meshfile import tidied_obj_text

    loose, cr_only = _layout(str(path), path.stat().st_mtime_ns)
    with open(path, "rb") as fh:
        for lines in _cr_blocks(fh) if cr_only else iter(lambda: fh.readlines(READ_BYTES), []):
            tidied = tidied_obj_text(b"".join(lines)) if loose else None
            yield lines if tidied is None else tidied.splitlines(keepends=True)


def _cr_blocks(fh) -> Iterator[list[bytes]]:
    """The lines of a file whose lines end in CR alone (classic Mac OS), a block at a time, ending in LF."""
    rest = b""
    while data := fh.read(READ_BYTES):
        data = rest + data
        cut = data.rfind(b"\r") + 1
        rest = data[cut:]
        if cut:
            yield data[:cut].replace(b"\r", b"\n").splitlines(keepends=True)
    if rest:
        yield rest.splitlines(keepends=True)


@lru_cache(maxsize=4)
def _layout(path: str, mtime_ns: int) -> tuple[bool, bool]:
    """(whether the OBJ starts with a byte order mark or holds a tab or an indented line, whether its
    lines end in CR alone, as its first block's do): one look at the file for both passes, read a
    block at a time (a map of the file would count it all in the job's peak memory)."""
    from pipeline25d.formats.meshfile import cr_only, needs_tidying

    with open(path, "rb") as fh:
        data = fh.read(READ_BYTES)
        crs = cr_only(data)
        loose, last = False, b""
        while data and not loose:           # each block with the byte before it: a line start across blocks
            text = last + (data.replace(b"\r", b"\n") if crs else data)
            loose, last, data = needs_tidying(text), text[-1:], fh.read(READ_BYTES)
    return loose, crs


_SPACE = np.zeros(256, dtype=bool)
_SPACE[list(b" \t\r\n\v\f")] = True                 # what bytes.split() splits on


class Words:
    """The words of OBJ lines (as ``line.split()`` cuts them), found on the lines' bytes at once: each
    word's first byte, the line it is on, whether it is its line's keyword, and the lines' text with
    the keywords blanked (numbers alone, for ``np.fromstring``). Each line but a file's last ends in
    a newline; each starts with its keyword (:func:`kinds`)."""

    def __init__(self, lines: list[bytes]):
        buf = np.frombuffer(b"".join(lines), dtype=np.uint8)
        space = _SPACE[buf]
        self.buf = buf
        self.starts = np.flatnonzero(~space & np.concatenate([[True], space[:-1]]))
        self.line_of = np.searchsorted(np.flatnonzero(buf == 10), self.starts)
        self.keyword = np.concatenate([[True], self.line_of[1:] != self.line_of[:-1]])[:len(self.starts)]
        self.count = np.bincount(self.line_of[~self.keyword], minlength=len(lines)).astype(np.int64)

    def numbers_text(self) -> bytes:
        """The lines' text with each keyword (``v``, ``vt`` or ``f``) blanked."""
        blank = self.buf.copy()
        at = self.starts[self.keyword]
        for _ in range(2):                                 # v, vt, f: at most two bytes
            blank[at] = 32
            at = at + 1
            at = at[at < len(blank)]
            at = at[~_SPACE[blank[at]]]                    # the keyword goes on
        return blank.tobytes()


def face_tokens(lines: list[bytes]) -> tuple[np.ndarray, np.ndarray, bytes]:
    """(corners of each face line, the slashes in each corner, the lines' text with their ``f`` blanked)."""
    words = Words(lines)
    corners = words.starts[~words.keyword]
    slashes = np.bincount(np.searchsorted(corners, np.flatnonzero(words.buf == 47), side="right") - 1,
                          minlength=len(corners))
    return words.count, slashes.astype(np.int64), words.numbers_text()
