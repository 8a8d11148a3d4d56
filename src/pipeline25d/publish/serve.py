"""A static file server that answers HTTP Range requests, for the viewer's PMTiles archives.

Python's ``http.server`` sends whole files and ignores ``Range``; a PMTiles archive is read by
byte ranges (its header, directories, then one range per tile), so the viewer in PMTiles mode
needs a server that answers them with ``206 Partial Content``. This one does for one range
(``bytes=a-b``, ``a-``, ``-n``), answers ``416`` to a range past the end and sends the whole file
for anything else, as RFC 9110 allows. ``pipeline25d serve results/demo`` serves a results folder
on 127.0.0.1:8000. Nothing outside the served folder is ever sent: ``..`` in a URL cannot climb
out (``http.server`` drops it), and a link inside the folder that resolves outside it is answered
404 like a missing file.
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import re
import shutil
import signal
from http import HTTPStatus
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import BinaryIO, Sequence

from pipeline25d.core.stopping import exit_on_sigterm

log = logging.getLogger(__name__)

_RANGE = re.compile(r"bytes=(\d*)-(\d*)")


def byte_range(header: str, size: int) -> tuple[int, int] | None | bool:
    """The inclusive (first, last) byte a ``Range`` header asks of a file of ``size`` bytes; None
    when the header is not one byte range (then the whole file is sent), False when the range
    starts past the end (416)."""
    m = _RANGE.fullmatch(header.strip())
    if m is None or m.group(1) == m.group(2) == "":
        return None
    if m.group(1) == "":                                    # the last n bytes
        n = int(m.group(2))
        return (max(size - n, 0), size - 1) if n > 0 and size > 0 else False
    first = int(m.group(1))
    last = size - 1 if m.group(2) == "" else min(int(m.group(2)), size - 1)
    if m.group(2) != "" and int(m.group(2)) < first:
        return None                                         # invalid: ignored, whole file
    return (first, last) if first < size else False


def _inside(path: str, root: str) -> bool:
    """Whether ``path``, links resolved, lies in the folder ``root`` (links resolved too)."""
    real_root = os.path.realpath(root)
    return os.path.commonpath([os.path.realpath(path), real_root]) == real_root


class RangeHandler(SimpleHTTPRequestHandler):
    """``SimpleHTTPRequestHandler`` plus single byte ranges; quiet unless ``verbose``."""

    verbose = False
    _left: int | None = None

    def log_message(self, format: str, *args) -> None:  # noqa: A002 (the http.server name)
        if self.verbose:
            super().log_message(format, *args)

    def send_head(self) -> BinaryIO | None:
        self._left = None
        header = self.headers.get("Range")
        path = self.translate_path(self.path)
        if not _inside(path, self.directory):
            self.send_error(HTTPStatus.NOT_FOUND, "File not found")
            return None
        if header is None or not os.path.isfile(path):
            return super().send_head()
        try:
            f = open(path, "rb")
        except OSError:
            self.send_error(HTTPStatus.NOT_FOUND, "File not found")
            return None
        size = os.fstat(f.fileno()).st_size
        span = byte_range(header, size)
        if span is None:
            f.close()
            return super().send_head()
        if span is False:
            f.close()
            self.send_response(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
            self.send_header("Content-Range", f"bytes */{size}")
            self.send_header("Content-Length", "0")
            self.end_headers()
            return None
        first, last = span
        self.send_response(HTTPStatus.PARTIAL_CONTENT)
        self.send_header("Content-Type", self.guess_type(path))
        self.send_header("Content-Range", f"bytes {first}-{last}/{size}")
        self.send_header("Content-Length", str(last - first + 1))
        self.send_header("Last-Modified", self.date_time_string(int(os.fstat(f.fileno()).st_mtime)))
        self.end_headers()
        f.seek(first)
        self._left = last - first + 1
        return f

    def end_headers(self) -> None:
        self.send_header("Accept-Ranges", "bytes")
        super().end_headers()

    def copyfile(self, source: BinaryIO, outputfile: BinaryIO) -> None:
        if self._left is None:
            shutil.copyfileobj(source, outputfile)
            return
        while self._left > 0:
            chunk = source.read(min(self._left, 1 << 16))
            if not chunk:
                break
            outputfile.write(chunk)
            self._left -= len(chunk)


def make_server(root: str | Path, host: str = "127.0.0.1", port: int = 8000,
                verbose: bool = False) -> ThreadingHTTPServer:
    """A threading HTTP server for the files under ``root`` (port 0: any free port)."""
    root = Path(root)
    if not root.is_dir():
        raise NotADirectoryError(f"{root}: not a folder to serve")
    handler = type("Handler", (RangeHandler,), {"verbose": verbose})
    return ThreadingHTTPServer((host, port), functools.partial(handler, directory=str(root)))


def serve_until_interrupted(server: ThreadingHTTPServer) -> None:
    """Serve until Ctrl-C (SIGINT) or SIGTERM, then close the server.

    Both are (re)armed here: a process started in the background by a shell without job control
    inherits SIGINT ignored, and Python then never raises KeyboardInterrupt, so ``kill -INT``
    would leave the server running."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    exit_on_sigterm()
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pipeline25d serve", description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="folder to serve, e.g. results/demo")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1, this machine only)")
    parser.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    server = make_server(args.root, args.host, args.port, verbose=True)
    log.info("serving %s at http://%s:%d/ (viewer: /viewer/index.html; Ctrl-C stops)", args.root,
             *server.server_address[:2])
    serve_until_interrupted(server)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
