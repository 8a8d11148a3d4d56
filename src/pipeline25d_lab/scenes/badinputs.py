"""The hostile-input corpus: broken model files, one folder per format, written deterministically.

``python -m pipeline25d_lab.scenes.badinputs OUTDIR`` writes it (the repository keeps it in
``tests/data/bad/``; ``tests/test_bad_inputs.py`` checks that it matches this module). Every
:class:`Case` is a model file that ingest must refuse with an error naming the file and the
problem, except the ``degenerate`` cases, whose zero-area triangles are dropped with a warning
while every other triangle is kept.

A format joins the corpus with one :class:`Format` entry in :data:`FORMATS`: a function that
writes a small model (vertices, triangles, an optional texture file name) in that format. The
common cases (:func:`common_cases`) are made from it; a format adds its own in ``extra``.

The writers of small models in every format are :mod:`pipeline25d_lab.scenes.model_writers`;
the cases of issue 27 (recovered defects, tree limits, side files) :mod:`pipeline25d_lab.scenes.hostile`.
"""

from __future__ import annotations

import json
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import CRSError, InputFileError, Pipeline25dError
from pipeline25d_lab.scenes.model_writers import (  # noqa: F401 - the corpus's writers, used by tests from here
    DEGENERATE,
    DEGENERATE_FACES,
    ECEF_ORIGIN,
    PNG_1PX,
    SCENE_CRS,
    SQUARE,
    SQUARE_FACES,
    Case,
    Writer,
    b3dm_bytes,
    glb_bytes,
    gltf_parts,
    tileset,
    write_3ds,
    write_b3dm,
    write_citygml,
    write_cityjson,
    write_dae,
    write_glb,
    write_gltf,
    write_obj,
    write_osgb,
    write_ply,
    write_slpk,
    write_tileset,
)

PHRASES = {"truncated": "truncated", "corrupt-header": "cannot read", "empty": "is empty",
           "nan": "NaN or infinite coordinates", "inf": "NaN or infinite coordinates",
           "degenerate": "dropped 2 of 4 triangles that are degenerate",
           "all-degenerate": "all 2 triangles are degenerate", "index-out-of-range": "out of range",
           "absurd-coordinates": "beyond any place on Earth", "missing-texture": "is missing",
           "texture-not-an-image": "not an image", "texture-truncated": "cannot be read"}


@dataclass(frozen=True)
class Format:
    """A format's place in the corpus: its folder and suffix, a writer of a small model, whether
    it carries textures, the phrases its messages use where they differ from :data:`PHRASES`,
    and cases of its own (``extra``)."""

    folder: str
    suffix: str
    write: Writer
    textures: bool = True
    phrases: dict[str, str] = field(default_factory=dict)
    without: frozenset[str] = frozenset()   # common cases the format has no form of
    extra: list[Case] = field(default_factory=list)


# --------------------------------------------------------------------------- cases


def _model(fmt: Format, v: np.ndarray, f: np.ndarray, texture: str | None = None) -> Callable[[Path], None]:
    return lambda path: fmt.write(path, v, f, texture)


def _truncated(fmt: Format) -> Callable[[Path], None]:
    """A valid model cut in the middle of a line (text) or of its data (binary)."""
    def write(path: Path) -> None:
        fmt.write(path, SQUARE, SQUARE_FACES, None)
        data = path.read_bytes()
        cut = len(data) * 2 // 3
        while data[cut - 1:cut] in (b"\n", b" "):
            cut += 1
        path.write_bytes(data[:cut])
    return write


def _corrupt_header(fmt: Format) -> Callable[[Path], None]:
    """A valid model whose first 16 bytes are garbage."""
    def write(path: Path) -> None:
        fmt.write(path, SQUARE, SQUARE_FACES, None)
        path.write_bytes(b"\x00\xffgarbage\x00\xff\x13\x37!!" + path.read_bytes()[16:])
    return write


def _texture_file(fmt: Format, data: bytes | None) -> Callable[[Path], None]:
    """A textured model whose image file beside it holds ``data`` (None: is not there)."""
    def write(path: Path) -> None:
        image = f"{path.stem}.png"
        fmt.write(path, SQUARE, SQUARE_FACES, image)
        if data is not None:
            path.with_name(image).write_bytes(data)
    return write


def _cut_png() -> bytes:
    """A 32 x 32 px PNG of noise cut off halfway: its signature and header are whole, its pixels not."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.random.default_rng(27).integers(0, 256, (32, 32, 3), dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue()[:len(buf.getvalue()) // 2]


def common_cases(fmt: Format) -> list[Case]:
    """The cases every format has, made with its writer."""
    d, s = fmt.folder, fmt.suffix
    with_nan, with_inf, huge = SQUARE.copy(), SQUARE.copy(), SQUARE.copy()
    with_nan[2, 1] = np.nan
    with_inf[1, 2] = np.inf
    huge[:, 0] += 1e12
    degenerate = np.vstack([SQUARE, DEGENERATE]), np.vstack([SQUARE_FACES, DEGENERATE_FACES])
    writers = {
        "truncated": _truncated(fmt),
        "corrupt-header": _corrupt_header(fmt),
        "empty": lambda path: path.write_bytes(b""),
        "nan": _model(fmt, with_nan, SQUARE_FACES),
        "inf": _model(fmt, with_inf, SQUARE_FACES),
        "degenerate": _model(fmt, *degenerate),
        "all-degenerate": _model(fmt, degenerate[0], DEGENERATE_FACES),
        "index-out-of-range": _model(fmt, SQUARE, np.array([[0, 1, 2], [0, 2, 9]])),
        "absurd-coordinates": _model(fmt, huge, SQUARE_FACES),
    }
    if fmt.textures:
        writers["missing-texture"] = _texture_file(fmt, None)
        writers["texture-not-an-image"] = _texture_file(fmt, b"GIF? no.\n")
        writers["texture-truncated"] = _texture_file(fmt, _cut_png())
    phrases = {**PHRASES, **fmt.phrases}
    cases = [Case(f"{d}/{kind}{s}", phrases[kind], write, None if kind == "degenerate" else InputFileError)
             for kind, write in writers.items() if kind not in fmt.without]
    return cases + fmt.extra


def _cycle(path: Path) -> None:
    """tileset.json -> other.json -> tileset.json, each also drawing a tile."""
    write_b3dm(path.with_name("tile.b3dm"), SQUARE, SQUARE_FACES, None)
    path.write_text(json.dumps(tileset("tile.b3dm", [{"boundingVolume": {"sphere": [*ECEF_ORIGIN, 100.0]},
                                                      "geometricError": 0, "content": {"uri": "other.json"}}])))
    path.with_name("other.json").write_text(json.dumps(tileset("tileset.json")))


def _missing_content(path: Path) -> None:
    path.write_text(json.dumps(tileset("nowhere.b3dm")))


def _package(path: Path, entries: dict[str, bytes]) -> None:
    """A zip of ``entries`` with fixed dates (the same bytes every time it is written)."""
    import zipfile

    with zipfile.ZipFile(path, "w") as z:
        for name, data in entries.items():
            z.writestr(zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0)), data)


def _tileset_entries(tile: bytes | None = None) -> dict[str, bytes]:
    """A one-tile tileset's files: its JSON and its b3dm (``tile`` in its place, when given)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        write_b3dm(Path(tmp) / "tile.b3dm", SQUARE, SQUARE_FACES, None)
        b3dm = (Path(tmp) / "tile.b3dm").read_bytes()
    return {"tileset.json": json.dumps(tileset("tile.b3dm")).encode(), "tile.b3dm": b3dm if tile is None else tile}


def _package_climbing_out(path: Path) -> None:
    _package(path, {**_tileset_entries(), "../escaped.b3dm": b"a tile written beside the package"})


def _package_without_tileset(path: Path) -> None:
    _package(path, {"readme.txt": b"a zip of something else"})


def _package_tile_cut(path: Path) -> None:
    _package(path, _tileset_entries(_tileset_entries()["tile.b3dm"][:40]))


def _outside_area(path: Path) -> None:
    """UTM coordinates labelled with the Dutch EPSG:28992: far outside that CRS's area of use."""
    write_cityjson(path, SQUARE, SQUARE_FACES, None)
    doc = json.loads(path.read_text())
    doc["metadata"]["referenceSystem"] = "https://www.opengis.net/def/crs/EPSG/0/28992"
    path.write_text(json.dumps(doc))


FORMATS: list[Format] = [
    Format("obj", ".obj", write_obj, phrases={"corrupt-header": "corrupt"}),
    Format("ply", ".ply", write_ply, textures=False),
    Format("dae", ".dae", write_dae, textures=False,
           phrases={"truncated": "malformed XML", "corrupt-header": "malformed XML",
                    "index-out-of-range": "beyond the limits"}),
    Format("glb", ".glb", write_glb, phrases={"corrupt-header": "neither GLB nor valid glTF JSON"}),
    Format("gltf", ".gltf", write_gltf, phrases={"truncated": "neither GLB nor valid glTF JSON",
                                                 "corrupt-header": "neither GLB nor valid glTF JSON"}),
    Format("b3dm", ".b3dm", write_b3dm, phrases={"corrupt-header": "unknown tile content format"}),
    Format("3dtiles", ".json", write_tileset,
           phrases={"truncated": "not valid JSON", "corrupt-header": "not valid JSON"},
           extra=[Case("3dtiles/cycle/tileset.json", "cycle", _cycle),
                  Case("3dtiles/missing-content.json", "is missing", _missing_content),
                  Case("3dtiles/entry-climbing-out.3tz", "lies outside the package", _package_climbing_out),
                  Case("3dtiles/no-tileset.zip", "without a tileset.json", _package_without_tileset),
                  Case("3dtiles/tile-cut-short.3tz", "tile-cut-short.3tz!/tile.b3dm", _package_tile_cut)]),
    Format("cityjson", ".city.json", write_cityjson, textures=False,
           phrases={"truncated": "not valid JSON", "corrupt-header": "not valid JSON"},
           extra=[Case("cityjson/outside-area-of-use.city.json", "outside the area of use", _outside_area,
                       CRSError)]),
    Format("osgb", ".osgb", write_osgb, without=frozenset({"nan", "inf"}),   # osgconv's text reader makes them numbers
           phrases={"truncated": "osgconv cannot read it", "corrupt-header": "osgconv cannot read it"}),
    Format("3ds", ".3ds", write_3ds, without=frozenset({"index-out-of-range"}),   # assimp will not write one
           phrases={"truncated": "assimp cannot read it", "corrupt-header": "assimp cannot read it",
                    "nan": "degenerate"}),                                        # assimp reads NaN as a point
    Format("citygml", ".gml", write_citygml, without=frozenset({"index-out-of-range"}),
           phrases={"truncated": "malformed XML", "corrupt-header": "malformed XML"}),
    Format("i3s", ".slpk", write_slpk, textures=False, without=frozenset({"index-out-of-range"}),  # no indices
           phrases={"truncated": "not a scene layer package", "corrupt-header": "cannot be read"}),
]


def cases() -> list[Case]:
    """Every case of every format, then the issue-27 ones (:mod:`pipeline25d_lab.scenes.hostile`), in a fixed order."""
    from pipeline25d_lab.scenes import hostile

    return [case for fmt in FORMATS for case in common_cases(fmt)] + hostile.cases()


def write_corpus(out: Path) -> list[Path]:
    """Write every case under ``out`` (overwriting its files); returns every file under ``out``."""
    out = Path(out)
    for case in cases():
        path = out / case.name
        path.parent.mkdir(parents=True, exist_ok=True)
        case.write(path)
    return sorted(p for p in out.rglob("*") if p.is_file())


def outcome(case: Case, corpus: Path) -> tuple[str, int]:
    """(message, exit status of the ingest job) of a case read from ``corpus``: the error's
    message, or for a case that loads the warning it gives (status 0)."""
    from pipeline25d.formats import load_district

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        try:
            load_district({"path": str(corpus / case.name)}, SCENE_CRS)
        except Pipeline25dError as exc:
            return str(exc), 1
    return "; ".join(str(w.message) for w in seen), 0


def table(corpus: Path) -> str:
    """The Markdown table of every case (case, message, exit status), paths relative to ``corpus``."""
    rows = ["| case | message | exit status |", "|---|---|---|"]
    corpus = Path(corpus).resolve()   # readers may name side files by absolute path
    for case in cases():
        message, status = outcome(case, corpus)
        message = message.replace(f"{corpus}/", "").replace("|", "\\|")
        rows.append(f"| `{case.name}` | {message} | {status} |")
    return "\n".join(rows) + "\n"


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """``OUTDIR``: write the corpus there; ``--table CORPUS``: print its table of outcomes."""
    import argparse

    parser = argparse.ArgumentParser(prog=prog, description="Write the hostile-input corpus, or print its table.")
    parser.add_argument("out_dir", nargs="?", type=Path, help="where the corpus goes, e.g. tests/data/bad")
    parser.add_argument("--table", type=Path, metavar="CORPUS", help="print the table of outcomes of a written corpus")
    args = parser.parse_args(argv)
    if args.table is not None:
        print(table(args.table), end="")
        return 0
    if args.out_dir is None:
        parser.error("give OUTDIR or --table CORPUS")
    for path in write_corpus(args.out_dir):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
