"""The issue-27 cases of the hostile-input corpus: real-world defects the readers recover from
(undeclared ADE prefixes, stray characters outside the geometry, missing children) and inputs
that must not hang, exhaust or escape (deep and exploding tile trees, deep JSON, side files
outside the input's folder). :func:`cases` joins :func:`pipeline25d_lab.scenes.badinputs.cases`;
:func:`measure` reads one case in a forked process and measures its time and peak memory.
"""

from __future__ import annotations

import json
import os
import resource
import time
import warnings
from collections.abc import Callable
from pathlib import Path

from pipeline25d.core.errors import UnsupportedFeatureError
from pipeline25d_lab.scenes import model_writers as W

DEEP = 3000          # levels of nesting of the deep JSON cases
FAN_OUT = (10, 6)    # names per tileset, tilesets: 10^6 tiles from seven files


def _citygml_with(extra: str, in_geometry: bool = False) -> Callable[[Path], None]:
    """A CityGML building (pretty-printed) with ``extra`` in its attributes, or with
    ``in_geometry`` spliced into its first coordinates."""
    def write(path: Path) -> None:
        b = W
        b.write_citygml(path, b.SQUARE, b.SQUARE_FACES, None)
        text = path.read_text().replace("><", ">\n<")
        if in_geometry:
            text = text.replace("<gml:posList>691000.0", f"<gml:posList>691000.0 {extra}", 1)
        else:
            text = text.replace('<bldg:Building gml:id="b1">', f'<bldg:Building gml:id="b1">\n{extra}', 1)
        path.write_text(text)
    return write


def _dae_with_stray(path: Path) -> None:
    b = W
    b.write_dae(path, b.SQUARE, b.SQUARE_FACES, None)
    path.write_text(path.read_text().replace("<asset>", "<asset>\n<contributor>\n<author>Smith & Sons&nbsp;"
                                                        "</author>\n</contributor>\n", 1))


def _osgb_missing_child(path: Path) -> None:
    """A .osgb whose PagedLOD draws the square inline up to 100 px and ``<stem>_L1.osgb`` (absent) beyond."""
    import itertools
    import tempfile

    from pipeline25d.formats.osgb import osgconv
    from pipeline25d_lab.scenes.osgb_sample import HEADER, geode_text

    b = W
    ids = itertools.count(2)
    geode = geode_text(ids, b.SQUARE, b.SQUARE_FACES, None, None)
    text = (HEADER + "osg::PagedLOD {\n UniqueID 1\n CenterMode USER_DEFINED_CENTER\n UserCenter 5 5 0 8\n"
            " RangeMode PIXEL_SIZE_ON_SCREEN\n RangeList 2 {\n  0 100\n  100 1e+30\n }\n DatabasePath FALSE\n"
            f' RangeDataList 2 {{\n  ""\n  "{path.stem}_L1.osgb"\n }}\n PriorityList 2 {{\n  0 1\n  0 1\n }}\n'
            f" Children 1 {{\n{geode}\n }}\n}}\n")
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "model.osgt").write_text(text)
        osgconv(Path("model.osgt"), Path("model.osgb"), [], Path(tmp), path)
        path.write_bytes((Path(tmp) / "model.osgb").read_bytes())


def _tile(content: str | None, children: list | None = None, refine: str = "REPLACE") -> dict:
    b = W
    tile: dict = {"boundingVolume": {"sphere": [*b.ECEF_ORIGIN, 100.0]}, "geometricError": 10 if children else 0,
                  "refine": refine}
    if content:
        tile["content"] = {"uri": content}
    if children:
        tile["children"] = children
    return tile


def _tileset(path: Path, root: dict) -> None:
    path.write_text(json.dumps({"asset": {"version": "1.0"}, "geometricError": 10, "root": root}))


def _unreachable_child(path: Path) -> None:
    b = W
    b.write_b3dm(path.with_name("parent.b3dm"), b.SQUARE, b.SQUARE_FACES, None)
    b.write_b3dm(path.with_name("child-a.b3dm"), b.SQUARE, b.SQUARE_FACES, None)
    _tileset(path, _tile("parent.b3dm", [_tile("child-a.b3dm"), _tile("child-b.b3dm")]))


def _deep_tileset(path: Path) -> None:
    path.write_text('{"asset":{"version":"1.0"},"geometricError":1,"root":' + '{"geometricError":1,"children":['
                    * DEEP + '{"geometricError":0}' + "]}" * DEEP + "}")


def _fan_out(path: Path) -> None:
    b = W
    names, files = FAN_OUT
    b.write_b3dm(path.with_name("leaf.b3dm"), b.SQUARE, b.SQUARE_FACES, None)
    _tileset(path.with_name(f"f{files}.json"), _tile("leaf.b3dm"))
    for k in range(files - 1, -1, -1):
        target = path if k == 0 else path.with_name(f"f{k}.json")
        _tileset(target, _tile(None, [_tile(f"f{k + 1}.json") for _ in range(names)]))


def _gltf_naming(buffer: str, image: str | None = None, beside: dict[str, bytes] | None = None,
                 link: tuple[str, str] | None = None) -> Callable[[Path], None]:
    """A glTF whose buffer URI is ``buffer`` (and image ``image``); ``beside``: files written
    relative to its folder; ``link``: (name, target) of a symlink beside it."""
    def write(path: Path) -> None:
        b = W
        doc, binary = b.gltf_parts(b.SQUARE, b.SQUARE_FACES, image)
        doc["buffers"][0]["uri"] = buffer
        path.write_text(json.dumps(doc))
        for name, data in (beside or {}).items():
            (path.parent / name).parent.mkdir(parents=True, exist_ok=True)
            (path.parent / name).write_bytes(binary if data == b"<buffer>" else data)
        if link:
            (path.parent / link[0]).unlink(missing_ok=True)
            (path.parent / link[0]).symlink_to(link[1])
    return write


def _cityjson_deep(path: Path) -> None:
    b = W
    b.write_cityjson(path, b.SQUARE, b.SQUARE_FACES, None)
    doc = json.loads(path.read_text())
    geometry = doc["CityObjects"]["b1"]["geometry"][0]
    geometry["boundaries"] = "<deep>"
    path.write_text(json.dumps(doc).replace('"<deep>"', "[" * DEEP + "0" + "]" * DEEP))


def _cityjson_texture_outside(path: Path) -> None:
    b = W
    b.write_cityjson(path, b.SQUARE, b.SQUARE_FACES, None)
    doc = json.loads(path.read_text())
    doc["appearance"] = {"textures": [{"type": "PNG", "image": "../outside.png"}],
                         "vertices-texture": [[0, 0], [1, 0], [1, 1], [0, 1]]}
    doc["CityObjects"]["b1"]["geometry"][0]["texture"] = {
        "t": {"values": [[[0, 0, 1, 2]], [[0, 0, 2, 3]]]}}
    path.write_text(json.dumps(doc))
    path.parent.with_name("outside.png").write_bytes(b.PNG_1PX)


def cases() -> list:
    """The issue-27 cases, in a fixed order (see docs/hostile-inputs.md)."""
    Case = W.Case
    png = W.PNG_1PX
    ade = '<energy:isHeated>true</energy:isHeated>'
    stray = '<ade:owner xmlns:ade="urn:example:ade">Smith & Sons&nbsp;\x01</ade:owner>'
    return [
        Case("citygml/undeclared-ade-prefix.gml", "undeclared namespace prefix energy", _citygml_with(ade), None),
        Case("citygml/stray-characters.gml", "stray character in <owner>", _citygml_with(stray), None),
        Case("citygml/stray-character-in-geometry.gml", "inside a geometry", _citygml_with("&", in_geometry=True)),
        Case("dae/stray-characters.dae", "stray character in <author>", _dae_with_stray, None),
        Case("osgb/missing-child.osgb", "1 PagedLOD child file(s) missing", _osgb_missing_child, None),
        Case("3dtiles/unreachable-child/tileset.json", "1 child content file(s) missing", _unreachable_child, None),
        Case("3dtiles/deep/tileset.json", "nested deeper than the JSON reader allows", _deep_tileset),
        Case("3dtiles/fan-out/tileset.json", "expands to more than 100000 tiles", _fan_out),
        Case("gltf/buffer-climbing-out/model.gltf", "lies outside the dataset folder",
             _gltf_naming("../buffer-climbing-out.bin", beside={"../buffer-climbing-out.bin": b"<buffer>"})),
        Case("gltf/texture-symlink/model.gltf", "lies outside the dataset folder",
             _gltf_naming("model.bin", "texture.png", {"model.bin": b"<buffer>", "../texture-symlink.png": png},
                          ("texture.png", "../texture-symlink.png"))),
        Case("gltf/absolute-uri.gltf", "lies outside the dataset folder", _gltf_naming("/etc/hostname")),
        Case("gltf/file-uri.gltf", "lies outside the dataset folder", _gltf_naming("file:///etc/hostname")),
        Case("gltf/http-uri.gltf", "is remote", _gltf_naming("http://example.com/model.bin"),
             UnsupportedFeatureError),
        Case("cityjson/deep-nesting.city.json", "nested deeper than the JSON reader allows", _cityjson_deep),
        Case("cityjson/texture-outside/model.city.json", "lies outside the dataset folder",
             _cityjson_texture_outside),
    ]


def measure(case, corpus: Path) -> dict:
    """Read ``case`` from ``corpus`` with ``load_district`` in a forked process: {message, status
    (1 refused, 0 read), error (its class name), seconds, peak_mb (the child's peak resident
    memory, ru_maxrss, which includes what it shares with this process)}."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:   # the child: read the case, report, leave without running any cleanup of the parent
        os.close(read)
        try:
            result = _read_case(case, corpus)
        except BaseException as exc:   # noqa: BLE001 - whatever it is, the parent must hear of it
            result = {"message": f"{type(exc).__name__}: {exc}", "status": 2, "error": "traceback"}
        result["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        os.write(write, json.dumps(result).encode())
        os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as f:
        data = f.read()
    os.waitpid(pid, 0)
    return json.loads(data)


def _read_case(case, corpus: Path) -> dict:
    from pipeline25d.core.errors import Pipeline25dError
    from pipeline25d.formats import load_district

    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        try:
            load_district({"path": str(corpus / case.name)}, W.SCENE_CRS)
            message, status, error = "; ".join(str(w.message) for w in seen), 0, None
        except Pipeline25dError as exc:
            message, status, error = str(exc), 1, type(exc).__name__
    return {"message": message, "status": status, "error": error, "seconds": time.perf_counter() - start}

