"""The PMTiles archive of a web-tile pyramid (every tile back, byte for byte, through the pmtiles
package's reader) and the Range-capable static server the viewer's PMTiles mode needs."""

from __future__ import annotations

import math
import threading
import urllib.error
import urllib.request

import pytest
from test_tms import _smooth_map

from pipeline25d.core.errors import InputFileError
from pipeline25d.publish.serve import byte_range, make_server
from pipeline25d.stages.tiles.archive import pyramid_tiles, write_pmtiles
from pipeline25d.stages.tiles.web import tms


@pytest.mark.parametrize("tile_format", ["webp", "png"])
def test_the_archive_holds_every_tile_of_the_pyramid_and_nothing_else(tmp_path, tile_format):
    from pmtiles.reader import MmapSource, Reader, all_tiles
    from pmtiles.tile import TileType

    _smooth_map(tmp_path / "map.tif")
    tms(tmp_path / "map.tif", "15-19", tmp_path / "tms", tile_format=tile_format)     # several zooms
    files = pyramid_tiles(tmp_path / "tms")
    assert len(files) == len(list((tmp_path / "tms").rglob(f"*.{tile_format}"))) > 20
    stats = write_pmtiles(tmp_path / "tms", tmp_path / "out" / "map.pmtiles", name="map")
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["map.pmtiles"]            # no temporary left
    with open(tmp_path / "out" / "map.pmtiles", "rb") as f:
        get = MmapSource(f)
        reader = Reader(get)
        header, metadata = reader.header(), reader.metadata()
        stored = {zxy: bytes(data) for zxy, data in all_tiles(get)}
        assert stored.keys() == files.keys()
        assert all(stored[zxy] == path.read_bytes() for zxy, path in files.items())
        assert all(bytes(reader.get(*zxy)) == stored[zxy] for zxy in files)             # the directory look-up
        assert reader.get(0, 0, 0) is None
    zooms = sorted({z for z, _, _ in files})
    assert (header["min_zoom"], header["max_zoom"]) == (zooms[0], zooms[-1]) == tuple(stats["zoom"])
    assert header["tile_type"] == TileType[tile_format.upper()] and header["clustered"]
    assert header["addressed_tiles_count"] == stats["tiles"] == len(files)
    assert header["tile_contents_count"] == stats["contents"] == len({p.read_bytes() for p in files.values()})
    assert metadata["name"] == "map" and metadata["format"] == tile_format
    # the header's bounds are those of the highest zoom's tiles (XYZ tile edges, computed here anew)
    top = [(x, y) for z, x, y in files if z == zooms[-1]]
    n = 2 ** zooms[-1]
    lat = lambda y: math.degrees(math.atan(math.sinh(math.pi * (1 - 2 * y / n))))      # noqa: E731
    expect = (min(x for x, _ in top) / n * 360 - 180, lat(max(y for _, y in top) + 1),
              (max(x for x, _ in top) + 1) / n * 360 - 180, lat(min(y for _, y in top)))
    got = tuple(header[k] / 1e7 for k in ("min_lon_e7", "min_lat_e7", "max_lon_e7", "max_lat_e7"))
    assert got == pytest.approx(expect, abs=1e-7)


def test_an_empty_or_mixed_pyramid_is_refused_naming_the_folder(tmp_path):
    (tmp_path / "tms" / "3" / "1").mkdir(parents=True)
    with pytest.raises(InputFileError, match="no web tiles"):
        write_pmtiles(tmp_path / "tms", tmp_path / "a.pmtiles")
    (tmp_path / "tms" / "3" / "1" / "2.png").write_bytes(b"p")
    (tmp_path / "tms" / "3" / "1" / "3.webp").write_bytes(b"w")
    with pytest.raises(InputFileError, match=r"tms: mixes tile formats"):
        write_pmtiles(tmp_path / "tms", tmp_path / "a.pmtiles")
    assert not list(tmp_path.glob("*a.pmtiles*"))


@pytest.mark.parametrize(("header", "size", "expect"), [
    ("bytes=0-9", 100, (0, 9)), ("bytes=90-", 100, (90, 99)), ("bytes=-10", 100, (90, 99)),
    ("bytes=50-500", 100, (50, 99)), ("bytes=-500", 100, (0, 99)), ("bytes=100-", 100, False),
    ("bytes=-0", 100, False), ("bytes=9-3", 100, None), ("bytes=0-1,5-6", 100, None), ("items=0-9", 100, None),
    ("bytes=-", 100, None)])
def test_byte_ranges_follow_rfc_9110(header, size, expect):
    assert byte_range(header, size) == expect


def test_the_server_answers_ranges_with_partial_content(tmp_path):
    data = bytes(range(256)) * 40
    (tmp_path / "a.bin").write_bytes(data)
    server = make_server(tmp_path, port=0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{server.server_address[1]}/a.bin"

    def get(rng: str | None) -> tuple[int, dict, bytes]:
        req = urllib.request.Request(url, headers={"Range": rng} if rng else {})
        try:
            with urllib.request.urlopen(req, timeout=10) as resp:
                return resp.status, dict(resp.headers), resp.read()
        except urllib.error.HTTPError as err:
            return err.code, dict(err.headers), err.read()

    try:
        status, headers, body = get("bytes=1000-1999")
        assert (status, body, headers["Content-Range"]) == (206, data[1000:2000], f"bytes 1000-1999/{len(data)}")
        assert headers["Content-Length"] == "1000" and headers["Accept-Ranges"] == "bytes"
        assert get("bytes=-7")[::2] == (206, data[-7:])
        assert get(f"bytes={len(data) - 3}-")[::2] == (206, data[-3:])
        status, headers, _ = get(f"bytes={len(data)}-")
        assert status == 416 and headers["Content-Range"] == f"bytes */{len(data)}"
        assert get(None)[::2] == (200, data) and get("bytes=0-1,5-6")[::2] == (200, data)
        assert get(None)[1]["Accept-Ranges"] == "bytes"
    finally:
        server.shutdown()
        server.server_close()
        thread.join()


def test_the_server_sends_nothing_from_outside_its_folder(tmp_path):
    """Neither ``..`` (plain or percent-encoded) nor a link inside the folder reaches a file outside it."""
    import http.client

    root, outside = tmp_path / "served", tmp_path / "secret"
    (root / "sub").mkdir(parents=True)
    outside.mkdir()
    (outside / "key.txt").write_bytes(b"SECRET")
    (root / "sub" / "a.txt").write_bytes(b"inside")
    (root / "leak.txt").symlink_to(outside / "key.txt")
    (root / "leakdir").symlink_to(outside, target_is_directory=True)
    (root / "inner.txt").symlink_to(root / "sub" / "a.txt")            # a link that stays inside is served
    server = make_server(root, port=0)
    threading.Thread(target=server.serve_forever, daemon=True).start()

    def get(path: str, rng: str | None = None) -> tuple[int, bytes]:
        conn = http.client.HTTPConnection("127.0.0.1", server.server_address[1], timeout=10)
        conn.request("GET", path, headers={"Range": rng} if rng else {})   # sent as written, not normalised
        resp = conn.getresponse()
        out = resp.status, resp.read()
        conn.close()
        return out

    try:
        for path in ("/../secret/key.txt", "/sub/../../secret/key.txt", "/%2e%2e/secret/key.txt",
                     "/%2E%2E%2Fsecret%2Fkey.txt", "//../secret/key.txt", "/leak.txt", "/leakdir/key.txt"):
            for rng in (None, "bytes=0-3"):
                status, body = get(path, rng)
                assert b"SECRET" not in body and b"SECR" not in body and status == 404, (path, rng, status)
        assert get("/sub/../sub/a.txt") == (200, b"inside") and get("/inner.txt", "bytes=0-1") == (206, b"in")
    finally:
        server.shutdown()
        server.server_close()
