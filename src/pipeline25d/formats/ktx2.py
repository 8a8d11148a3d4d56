"""KTX2 images with Basis Universal data (glTF's ``KHR_texture_basisu``), decoded to RGBA.

Cesium ion and gltfpack ``-tc`` write textures this way. Basis Universal's own transcoder (Binomial's,
in WebAssembly, as the ``three`` npm package ships it; ``make deps`` installs it) runs in one Node
process per Python process, started at the first KTX2 image and fed images through a pipe
(``ktx2_decode.cjs``): a tileset's thousands of textures pay Node's start once. Level 0 is taken,
top row first, as glTF requires KTX2 images to be stored. The header is checked here first: a file
that is not KTX2, holds no Basis Universal data (a ``vkFormat`` of its own) or claims more than
:data:`MAX_SIDE` pixels a side is refused without being decoded.
"""

from __future__ import annotations

import atexit
import io
import os
import shutil
import struct
import subprocess
import tempfile
import threading
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import Pipeline25dError
from pipeline25d.core.node_modules import package_folder

MAGIC = b"\xabKTX 20\xbb\r\n\x1a\n"
MAX_SIDE = 16384                 # pixels a side (a 1 GiB RGBA image)
TRANSCODER = ("three", "examples/jsm/libs/basis", ("basis_transcoder.js", "basis_transcoder.wasm"))
_SCRIPT = Path(__file__).with_name("ktx2_decode.cjs")


class Ktx2Error(ValueError):
    """Why a KTX2 image cannot be decoded (the caller names the file)."""


def is_ktx2(data: bytes) -> bool:
    """Whether ``data`` begins with KTX 2.0's identifier."""
    return data[:12] == MAGIC


def check_header(data: bytes) -> tuple[int, int]:
    """(width, height) of a KTX2 file holding Basis Universal data; Ktx2Error otherwise."""
    if not is_ktx2(data) or len(data) < 80:
        raise Ktx2Error("not a KTX2 file" if not is_ktx2(data) else "its header is cut short")
    vk_format, _, width, height = struct.unpack_from("<4I", data, 12)
    if vk_format != 0:
        raise Ktx2Error(f"its vkFormat is {vk_format}, not Basis Universal data (vkFormat 0), which "
                        "KHR_texture_basisu requires")
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise Ktx2Error(f"its size {width} x {height} is not within 1 to {MAX_SIDE} pixels a side")
    return width, height


def decode_ktx2(data: bytes) -> np.ndarray:
    """(h, w, 3) or, with alpha, (h, w, 4) uint8 pixels of a KTX2 image's level 0, top row first."""
    width, height = check_header(data)
    w, h, alpha, pixels = _transcoder().decode(data)
    if (w, h) != (width, height):
        raise Ktx2Error(f"its transcoded size {w} x {h} is not its header's {width} x {height}")
    rgba = np.frombuffer(pixels, np.uint8).reshape(h, w, 4)
    return rgba if alpha else rgba[..., :3]


def ktx2_as_png(data: bytes) -> bytes:
    """A KTX2 image as PNG bytes (what the chunks and the render job take)."""
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(decode_ktx2(data)).save(out, format="PNG", compress_level=1)
    return out.getvalue()


class _Transcoder:
    """The Node process that decodes, started on first use (again in a forked child, whose parent's
    pipes are not its own) and ended at exit."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        self._err = None                     # a temporary file holding Node's stderr
        self._pid = 0
        self._lock = threading.Lock()

    def decode(self, data: bytes) -> tuple[int, int, int, bytes]:
        with self._lock:
            proc = self._started()
            try:
                proc.stdin.write(struct.pack("<I", len(data)) + data)
                proc.stdin.flush()
                status, a, b, alpha = struct.unpack("<4I", _read(proc.stdout, 16))
                if status:
                    raise Ktx2Error(_read(proc.stdout, a).decode("utf-8", "replace"))
                return a, b, alpha, _read(proc.stdout, a * b * 4)
            except (OSError, EOFError) as exc:
                why = self._stderr() or exc
                self.close()
                raise Ktx2Error(f"the Basis Universal transcoder (Node) stopped: {why}") from None

    def _started(self) -> subprocess.Popen:
        if self._proc is not None and self._pid == os.getpid() and self._proc.poll() is None:
            return self._proc
        self.close()                       # one that ended: its pipes and stderr file (a child's: forgotten)
        node = shutil.which("node")
        if node is None:
            raise Ktx2Error("decoding Basis Universal textures needs Node.js (`node` on PATH; `make deps` "
                            "installs it with npm)")
        try:
            folder = package_folder(*TRANSCODER)
        except Pipeline25dError as exc:
            raise Ktx2Error(f"the Basis Universal transcoder is missing: {exc}") from None
        self._err = tempfile.TemporaryFile()
        self._proc = subprocess.Popen([node, str(_SCRIPT), str(folder)], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=self._err)
        self._pid = os.getpid()
        return self._proc

    def _stderr(self) -> str:
        if self._err is None:
            return ""
        self._err.seek(0)
        return self._err.read()[-500:].decode("utf-8", "replace").strip()

    def close(self) -> None:
        """End the Node process (this process's own only; a forked child leaves its parent's alone)."""
        proc, err, self._proc, self._err = self._proc, self._err, None, None
        if self._pid != os.getpid():
            return
        if proc is not None:
            for stream in (proc.stdin, proc.stdout):
                stream.close()
            proc.kill()
            proc.wait()
        if err is not None:
            err.close()


def _read(stream, n: int) -> bytes:
    data = stream.read(n)
    if len(data) != n:
        raise EOFError(f"{len(data)} of {n} bytes")
    return data


_TRANSCODER = _Transcoder()
atexit.register(_TRANSCODER.close)


def _transcoder() -> _Transcoder:
    return _TRANSCODER
