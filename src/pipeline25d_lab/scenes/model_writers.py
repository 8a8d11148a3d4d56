"""Small models written in every input format, for the hostile-input corpus
(:mod:`pipeline25d_lab.scenes.badinputs`, :mod:`pipeline25d_lab.scenes.hostile`): a 10 m square
(two triangles) or any vertices and triangles, and :class:`Case`, one file of the corpus."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError

Writer = Callable[[Path, np.ndarray, np.ndarray, str | None], None]

#: A model of two triangles (a 10 m square at the origin, z up); scenes place it with ``offset``.
SQUARE = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], dtype=np.float64)
SQUARE_FACES = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
#: Two more vertices and two triangles with no area: a repeated vertex, three on one line.
DEGENERATE = np.array([[5, 5, 0], [20, 20, 0]], dtype=np.float64)
DEGENERATE_FACES = np.array([[0, 0, 1], [0, 4, 5]], dtype=np.int64)
#: a 1 x 1 white RGBA PNG that decodes (its zlib data and checksums whole)
PNG_1PX = bytes.fromhex("89504e470d0a1a0a0000000d4948445200000001000000010806000000"
                        "1f15c4890000000d49444154789c63f8ffffff7f0009fb03fd2a86e38a"
                        "0000000049454e44ae426082")


@dataclass(frozen=True)
class Case:
    """One hostile file: ``name`` its path in the corpus (the model the input points at),
    ``problem`` a phrase the error message must contain, ``error`` the exception class
    (None: no error, ``problem`` is the warning), ``write`` what writes it (and its side files)."""

    name: str
    problem: str
    write: Callable[[Path], None]
    error: type[Exception] | None = InputFileError


#: What the message of each common case says, unless a format's ``phrases`` say otherwise.

# --------------------------------------------------------------------------- writers


def write_obj(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """An OBJ (with an .mtl and UVs when ``texture`` names an image file)."""
    lines = []
    if texture:
        mtl = path.with_suffix(".mtl")
        mtl.write_text(f"newmtl skin\nKd 1 1 1\nmap_Kd {texture}\n")
        lines += [f"mtllib {mtl.name}", "usemtl skin"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in v.tolist()]
    if texture:
        lines += [f"vt {x / 10:g} {y / 10:g}" for x, y, _ in v.tolist()]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in f.tolist()]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f.tolist()]
    path.write_text("\n".join(lines) + "\n")


def write_ply(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """A binary little-endian PLY (float64 positions, int32 triangles)."""
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\nproperty double x\n"
              f"property double y\nproperty double z\nelement face {len(f)}\n"
              "property list uchar int vertex_indices\nend_header\n")
    faces = b"".join(struct.pack("<B3i", 3, *tri) for tri in f.tolist())
    path.write_bytes(header.encode() + np.asarray(v, "<f8").tobytes() + faces)


def write_dae(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """A minimal COLLADA 1.4 file (one geometry, one node)."""
    floats = " ".join(repr(x) for x in v.ravel().tolist())
    indices = " ".join(str(i) for i in f.ravel().tolist())
    path.write_text(f"""<?xml version="1.0" encoding="utf-8"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
 <asset><unit meter="1" name="meter"/><up_axis>Z_UP</up_axis></asset>
 <library_geometries><geometry id="g"><mesh>
  <source id="p"><float_array id="pa" count="{v.size}">{floats}</float_array>
   <technique_common><accessor source="#pa" count="{len(v)}" stride="3">
    <param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>
   </accessor></technique_common></source>
  <vertices id="v"><input semantic="POSITION" source="#p"/></vertices>
  <triangles count="{len(f)}"><input semantic="VERTEX" source="#v" offset="0"/><p>{indices}</p></triangles>
 </mesh></geometry></library_geometries>
 <library_visual_scenes><visual_scene id="s"><node id="n"><instance_geometry url="#g"/></node></visual_scene>
 </library_visual_scenes>
 <scene><instance_visual_scene url="#s"/></scene>
</COLLADA>
""")


def gltf_parts(v: np.ndarray, f: np.ndarray, texture: str | None) -> tuple[dict, bytes]:
    """(glTF JSON, binary buffer) of a mesh stored y-up ((x, y, z) as (x, z, -y)), float32
    positions, uint32 indices, and UVs with an external image when ``texture`` is given."""
    pos = np.column_stack([v[:, 0], v[:, 2], -v[:, 1]]).astype("<f4")
    idx = np.asarray(f, "<u4").ravel()
    uv = (v[:, :2] / 10).astype("<f4")
    blobs = [pos.tobytes(), idx.tobytes()] + ([uv.tobytes()] if texture else [])
    views, offset = [], 0
    for blob in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        offset += len(blob)
    finite = pos[np.isfinite(pos).all(axis=1)]
    lo, hi = (finite.min(axis=0), finite.max(axis=0)) if len(finite) else (np.zeros(3), np.zeros(3))
    accessors = [{"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
                  "min": lo.tolist(), "max": hi.tolist()},
                 {"bufferView": 1, "componentType": 5125, "count": len(idx), "type": "SCALAR"}]
    prim: dict = {"attributes": {"POSITION": 0}, "indices": 1}
    doc: dict = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
                 "meshes": [{"primitives": [prim]}], "bufferViews": views, "accessors": accessors,
                 "buffers": [{"byteLength": offset}]}
    if texture:
        accessors.append({"bufferView": 2, "componentType": 5126, "count": len(uv), "type": "VEC2"})
        prim["attributes"]["TEXCOORD_0"] = 2
        prim["material"] = 0
        doc.update(materials=[{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
                   textures=[{"source": 0}], images=[{"uri": texture}])
    return doc, b"".join(blobs)


def glb_bytes(doc: dict, binary: bytes) -> bytes:
    """A GLB container of a glTF JSON and its binary buffer."""
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def write_glb(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    path.write_bytes(glb_bytes(*gltf_parts(v, f, texture)))


def write_gltf(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """A JSON glTF with its buffer in a .bin file beside it."""
    doc, binary = gltf_parts(v, f, texture)
    path.with_suffix(".bin").write_bytes(binary)
    doc["buffers"][0]["uri"] = path.with_suffix(".bin").name
    path.write_text(json.dumps(doc, indent=1))


def b3dm_bytes(glb: bytes) -> bytes:
    """A b3dm tile (empty feature and batch tables) around a GLB."""
    return struct.pack("<4s6I", b"b3dm", 1, 28 + len(glb), 0, 0, 0, 0) + glb


#: The scene CRS of the corpus; the 3D Tiles and b3dm cases stand in ECEF at 48.1° N 11.6° E,
#: the CityJSON ones at 691000 E 5334000 N, both inside its area of use.
SCENE_CRS = "EPSG:25832"
ECEF_ORIGIN = (4180627.0, 858159.0, 4724696.0)


def write_b3dm(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """A b3dm whose GLB is placed in ECEF by CESIUM_RTC (its image, if any, beside the tile)."""
    doc, binary = gltf_parts(v, f, texture)
    doc["extensionsUsed"] = ["CESIUM_RTC"]
    doc["extensions"] = {"CESIUM_RTC": {"center": list(ECEF_ORIGIN)}}
    path.write_bytes(b3dm_bytes(glb_bytes(doc, binary)))


def tileset(content: str | None, children: list[dict] | None = None) -> dict:
    """A tileset JSON whose root draws ``content`` (a URI) with optional children; its
    geometric error (100 m with children) has every map refine it into them."""
    root: dict = {"boundingVolume": {"sphere": [*ECEF_ORIGIN, 100.0]}, "geometricError": 100 if children else 0,
                  "refine": "ADD"}
    if content:
        root["content"] = {"uri": content}
    if children:
        root["children"] = children
    return {"asset": {"version": "1.0"}, "geometricError": 100, "root": root}


def write_tileset(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """A tileset.json with one b3dm content tile (``<stem>.b3dm`` beside it)."""
    tile = path.with_name(f"{path.stem}.b3dm")
    write_b3dm(tile, v, f, texture)
    path.write_text(json.dumps(tileset(tile.name), indent=1))


def write_cityjson(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """A CityJSON 2.0 file (EPSG:25832, no transform) with one building of triangles."""
    doc = {"type": "CityJSON", "version": "2.0",
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/25832"},
           "CityObjects": {"b1": {"type": "Building", "geometry": [
               {"type": "MultiSurface", "lod": "1", "boundaries": [[tri] for tri in f.tolist()]}]}},
           "vertices": [[x + 691000, y + 5334000, z + 520] for x, y, z in v.tolist()]}
    path.write_text(json.dumps(doc))


def write_citygml(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """A CityGML 2.0 file (EPSG:25832) with one building whose triangles are polygons of a
    lod2MultiSurface, textured by a ParameterizedTexture when ``texture`` names an image file.
    Coordinates are inline, so an index out of range has no CityGML form."""
    pos = v + (691000, 5334000, 520)
    polygons, targets = [], []
    for k, tri in enumerate(f.tolist()):
        ring = " ".join(" ".join(repr(float(c)) for c in pos[i]) for i in [*tri, tri[0]])
        polygons.append(f'<gml:surfaceMember><gml:Polygon gml:id="p{k}"><gml:exterior><gml:LinearRing gml:id="r{k}">'
                        f'<gml:posList>{ring}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>'
                        '</gml:surfaceMember>')
        st = " ".join(f"{x / 10:g} {y / 10:g}" for x, y, _ in v[[*tri, tri[0]]].tolist())
        targets.append(f'<app:target uri="#p{k}"><app:TexCoordList>'
                       f'<app:textureCoordinates ring="#r{k}">{st}</app:textureCoordinates>'
                       '</app:TexCoordList></app:target>')
    appearance = "" if texture is None else (
        '<app:appearanceMember><app:Appearance><app:theme>rgb</app:theme><app:surfaceDataMember>'
        f'<app:ParameterizedTexture><app:imageURI>{texture}</app:imageURI>{"".join(targets)}'
        '</app:ParameterizedTexture></app:surfaceDataMember></app:Appearance></app:appearanceMember>')
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" '
        'xmlns:bldg="http://www.opengis.net/citygml/building/2.0" '
        'xmlns:app="http://www.opengis.net/citygml/appearance/2.0" xmlns:gml="http://www.opengis.net/gml">\n'
        '<core:cityObjectMember><bldg:Building gml:id="b1"><bldg:lod2MultiSurface>'
        '<gml:MultiSurface srsName="urn:ogc:def:crs:EPSG::25832" srsDimension="3">'
        f'{"".join(polygons)}</gml:MultiSurface></bldg:lod2MultiSurface></bldg:Building></core:cityObjectMember>\n'
        f'{appearance}\n</core:CityModel>\n')


def write_3ds(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """An Autodesk .3ds: the model written as OBJ (+ MTL) and converted by assimp (Debian
    assimp-utils), as the .3ds reader reads it back."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        obj = Path(tmp) / "model.obj"
        write_obj(obj, v, f, texture)
        proc = subprocess.run(["assimp", "export", obj.name, "model.3ds"], cwd=tmp, capture_output=True, text=True)
        if proc.returncode or not (Path(tmp) / "model.3ds").is_file():
            raise RuntimeError(f"assimp could not write {path.name}: {proc.stdout[-300:]} {proc.stderr[-300:]}")
        path.write_bytes((Path(tmp) / "model.3ds").read_bytes())


def _png() -> bytes:
    """A 2 x 2 grey PNG."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (2, 2), (128, 128, 128)).save(buf, format="PNG")
    return buf.getvalue()


def write_osgb(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """A single .osgb (OpenSceneGraph binary) of one Geode, written as osgt text and converted by
    osgconv (Debian openscenegraph); a texture is referenced by file name, as ContextCapture's are."""
    import itertools
    import tempfile

    from pipeline25d.formats.osgb import osgconv
    from pipeline25d_lab.scenes.osgb_sample import HEADER, geode_text

    uv = v[:, :2] / 10.0
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "model.osgt"
        src.write_text(HEADER + geode_text(itertools.count(1), v, f, uv, texture))
        if texture is not None:   # osgconv drops an image it cannot load; the .osgb only names it
            Path(tmp, texture).write_bytes(_png())
        osgconv(Path(src.name), Path("model.osgb"), ["WriteImageHint=UseExternal"], Path(tmp), path)
        path.write_bytes((Path(tmp) / "model.osgb").read_bytes())


def write_slpk(path: Path, v: np.ndarray, f: np.ndarray, texture: str | None) -> None:
    """An I3S scene layer package (EPSG:25832, 1.7 node pages) of one node holding the triangles
    (three vertices each, as I3S stores them), offsets from the node's centre as ArcGIS writes them."""
    import gzip
    import zipfile

    origin = np.array([691000.0, 5334000.0, 520.0])
    corners = v[f].reshape(-1, 3) + origin
    with np.errstate(invalid="ignore"):
        centre = (np.nanmin(corners, 0) + np.nanmax(corners, 0)) / 2
    centre = np.where(np.isfinite(centre), centre, origin)
    data = np.array([len(corners), 0], "<u4").tobytes() + (corners - centre).astype("<f4").tobytes()
    layer = {"layerType": "3DObject", "spatialReference": {"wkid": 25832},
             "nodePages": {"nodesPerPage": 64, "lodSelectionMetricType": "maxScreenThresholdSQ"},
             "geometryDefinitions": [{"geometryBuffers": [{"offset": 8,
                                                           "position": {"type": "Float32", "component": 3}}]}]}
    node = {"index": 0, "obb": {"center": centre.tolist(), "halfSize": [10, 10, 1], "quaternion": [0, 0, 0, 1]},
            "mesh": {"geometry": {"definition": 0, "resource": 0}}}
    entries = {"3dSceneLayer.json.gz": json.dumps(layer).encode(), "nodepages/0.json.gz": json.dumps(
        {"nodes": [node]}).encode(), "nodes/0/geometries/0.bin.gz": data}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for name, content in entries.items():              # a fixed date: the same bytes every time
            z.writestr(zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0)), gzip.compress(content, mtime=0))
