"""The workflow's building heights: which footprints, which reference, and the stage that measures them.

Footprints (config ``heights.footprints``): a user OGR polygon layer, or ``auto`` = the
buildings the inputs themselves know: the demo city's ``truth.json`` (beside its OBJs, found
through their ``manifest.json``) and CityJSON Building objects (outline of their GroundSurface,
else of all their surfaces projected to the ground).

Basis: :mod:`pipeline25d.analysis.heights` measures how far a roof moved between the nadir and an
oblique map, i.e. its height above the ground the maps were rendered over (the DTM of the
scene, ``scene.json`` "dtm", or the plane z0 with ``terrain: flat``), averaged under the roof.
Every reference is therefore put on that basis: roof z minus the mean of that DTM under the
outline (:func:`dtm_under`). Where the model has its own ground (the demo's analytic terrain,
3dfier's terrain where the walls meet it) the figures against it are reported as well.

Reference (``heights.reference``): ``auto`` = the demo's truth (flat roofs: the roof; pitched
roofs: the measured height against the eave and the measured ridge against the ridge, a group per
roof kind), else the roofs of an OBJ input with 3dfier materials (roof
material ``Building``), else the roofs of CityJSON buildings (RoofSurface), else the model's
DSM median inside the footprint; a path = a CSV ``id,height`` (taken to be on the maps' basis)
or a 3dfier OBJ; ``none`` = no comparison.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.analysis.ground_under import Sampler, dsm_roof, dtm_under, ground_range_under, ground_sampler
from pipeline25d.analysis.heights.results import MatchSettings
from pipeline25d.core.errors import InputFileError
from pipeline25d.formats.footprints import Footprint, RefBuilding, read_footprints
from pipeline25d.stages.records import Scene

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- what the config asks for

def has_nadir(config: dict) -> bool:
    from pipeline25d.config import perspectives

    return any(p.elevation == 90 for p in perspectives(config))


def demo_truths(config: dict, base_dir: Path = Path(".")) -> list[Path]:
    """truth.json files of the demo/rugged cities whose OBJs the inputs name (via their manifest.json)."""
    out: list[Path] = []
    for spec in config["inputs"].values():
        path = base_dir / spec["path"]
        try:
            manifest = json.loads((path.parent / "manifest.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(manifest, dict) or not manifest.get("truth"):
            continue
        if path.name in (manifest.get("districts") or {}).values():
            truth = path.parent / str(manifest["truth"])
            if truth.is_file() and truth not in out:
                out.append(truth)
    return out


def _inputs_of(config: dict, fmt: str, suffixes: tuple[str, ...]) -> list[str]:
    names = []
    for name, spec in sorted(config["inputs"].items()):
        f = spec.get("format", "auto")
        if f == fmt or (f == "auto" and spec["path"].lower().endswith(suffixes)):
            names.append(name)
    return names


def cityjson_inputs(config: dict) -> list[str]:
    """Districts that are CityJSON (by format key, or .json/.jsonl holding CityJSON)."""
    from pipeline25d.formats import detect_format

    out = []
    for name in _inputs_of(config, "cityjson", (".json", ".jsonl")):
        spec = config["inputs"][name]
        if spec.get("format") == "cityjson":
            out.append(name)
            continue
        try:
            if detect_format(Path(spec["path"])) == "cityjson":
                out.append(name)
        except InputFileError:
            pass
    return out


def plan(config: dict, base_dir: Path = Path(".")) -> dict[str, Any]:
    """What the heights step does, from the config alone (when the DAG is built):
    ``skip`` (a reason or None), ``footprints`` {source: layer|truth|cityjson, paths},
    ``reference`` {source: auto|csv|obj|none, path} and ``files`` (inputs of the rule)."""
    h = config.get("heights") or {}
    fp, ref = h.get("footprints", "auto"), h.get("reference", "auto")
    out: dict[str, Any] = {"skip": None, "footprints": None, "reference": None, "files": []}
    if fp == "none":
        out["skip"] = "heights.footprints is none"
    elif not has_nadir(config):
        out["skip"] = "no nadir perspective (azimuth 0, elevation 90) to measure roofs against"
    elif fp == "auto":
        truths = demo_truths(config, base_dir)
        cj = cityjson_inputs(config)
        if truths:
            out["footprints"] = {"source": "truth", "paths": [str(t) for t in truths]}
            out["files"] += [str(t) for t in truths]
        elif cj:
            out["footprints"] = {"source": "cityjson", "districts": cj}
        else:
            out["skip"] = ("no footprints: heights.footprints is auto and the inputs know no buildings "
                           "(no demo truth.json, no CityJSON); give a footprint layer")
    else:
        out["footprints"] = {"source": "layer", "paths": [fp], "layer": h.get("layer"), "id_field": h.get("id_field")}
        out["files"].append(fp)
    if out["skip"] is None:
        if ref in ("auto", "none"):
            out["reference"] = {"source": ref}
        else:
            kind = "obj" if ref.lower().endswith(".obj") else "csv"
            out["reference"] = {"source": kind, "path": ref}
            out["files"].append(ref)
    return out


# --------------------------------------------------------------------------- footprints and model heights

def truth_buildings(truth_path: str | Path, config: dict, scene_crs: str) -> dict[str, RefBuilding]:
    """The buildings of a generated scene's ``truth.json`` in the districts among the inputs, with
    the input's offset and CRS applied.

    Each building gives its ``footprint`` (x, y corners), its roof as ``eave_z`` (pitched roofs,
    with ``ridge_z`` and ``roof``) or ``roof_z`` (flat roofs), and ``own_ground_z``: the
    generator's exact terrain averaged under the outline (NaN where absent).
    """
    from pipeline25d.core.crs import transform_points

    truth_path = Path(truth_path)
    try:
        truth = json.loads(truth_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputFileError(truth_path, f"cannot read the scene's truth: {exc}") from None
    by_file = {Path(spec["path"]).name: spec for spec in config["inputs"].values()
               if (Path(spec["path"]).parent / truth_path.name).resolve() == truth_path.resolve()}
    districts = {name: by_file[d["obj"]] for name, d in (truth.get("districts") or {}).items()
                 if d.get("obj") in by_file}
    out: dict[str, RefBuilding] = {}
    for b in truth.get("buildings") or []:
        spec = districts.get(b.get("district"))
        if spec is None:
            continue
        roof = b["eave_z"] if "eave_z" in b else b.get("roof_z")
        if roof is None:
            raise InputFileError(truth_path, f"building {b.get('id')!r} has neither eave_z nor roof_z")
        corners = np.asarray(b["footprint"], dtype=np.float64)
        offset = np.asarray(spec.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)
        pts = np.column_stack([corners, np.full(len(corners), float(roof))]) + offset
        src = spec.get("crs") or truth.get("crs") or scene_crs
        if src != scene_crs:
            pts = transform_points(pts, src, scene_crs)
        dz = float(offset[2])
        out[str(b["id"])] = RefBuilding(Footprint(str(b["id"]), (np.ascontiguousarray(pts[:, :2]),)),
                                        float(roof) + dz, str(b.get("roof", "flat")),
                                        float(b.get("ridge_z", roof)) + dz,
                                        float(b.get("own_ground_z", math.nan)) + dz)
    return out


def obj_roofs(path: str | Path, offset_z: float = 0.0) -> dict[str, RefBuilding]:
    """Roofs of a 3dfier-style OBJ (per ``o`` object, see :func:`heights.obj_roof_ground`), no footprint."""
    from pipeline25d.analysis.heights.reference import obj_roof_ground

    return {k: RefBuilding(None, roof + offset_z, own_ground_z=ground + offset_z)
            for k, (roof, ground) in obj_roof_ground(path).items()}




# --------------------------------------------------------------------------- statistics

def group_stats(rows: list, reference: dict[str, float], views: list[str], ridge: bool = False) -> dict[str, Any]:
    """Per view and combined: n measured / n footprints of the group, and the error statistics
    (:func:`heights.error_stats`) over the buildings measured in it. ``reference``: {id: height}
    of the group's buildings (NaN: no reference; they count as footprints, not in the errors).
    ``ridge``: the measured ridges (``HeightRow.ridge``, ``ridges``) instead of the heights."""
    from pipeline25d.analysis.heights.reference import error_stats

    by_id = {r.id: r for r in rows}
    ids = [i for i in reference if i in by_id]
    ref = np.array([reference[i] for i in ids], dtype=np.float64)

    def one(get) -> dict:
        h = np.array([get(by_id[i]) for i in ids], dtype=np.float64)
        return {"n_footprints": len(ids), "n_measured": int(np.count_nonzero(np.isfinite(h))),
                **error_stats(h, ref)}

    out = {"combined": one(lambda r: r.ridge if ridge else r.height)}
    for v in views:
        out[v] = one(lambda r, v=v: (r.ridges if ridge else r.heights).get(v, math.nan))
    return out


# --------------------------------------------------------------------------- the stage

#: roof kinds with an eave and a ridge (compared with both)
PITCHED = ("gabled", "hipped")
#: the one definition of a building's height on sloped ground, in the CSV, the JSON and the report
BASIS = ("roof z (flat roofs; the eave of pitched roofs) minus the MEAN of the ground the maps used under "
         "the footprint; beside it, in the CSV, the same roof above the lowest and above the highest "
         "ground under the footprint (the downhill and the uphill wall height)")

#: what "the model's own ground" is, by the kind of reference
OWN_GROUND = {"truth": "the generator's exact terrain averaged under the outline (truth.json own_ground_z)",
              "obj": "the model's terrain where the building's walls meet it (3dfier)",
              "cityjson": "the building's own ground surfaces"}

def _nadir_extent(path: str | Path) -> tuple[float, float, float, float]:
    from pipeline25d.core.raster import dataset_bounds, gdal

    return dataset_bounds(gdal().Open(str(path)))


def _within(b: tuple[float, float, float, float], ext: tuple[float, float, float, float]) -> bool:
    return b[0] >= ext[0] and b[1] >= ext[1] and b[2] <= ext[2] and b[3] <= ext[3]


def load_buildings(p: dict, config: dict) -> tuple[list[Footprint], dict[str, RefBuilding]]:
    """Footprints and the model's own buildings (empty where the footprints are a user layer)."""
    src = p["footprints"]
    crs = config["crs"]
    if src["source"] == "layer":
        fps = read_footprints(src["paths"][0], src.get("layer"), src.get("id_field"), crs=crs)
        return fps, {}
    model: dict[str, RefBuilding] = {}
    if src["source"] == "truth":
        for t in src["paths"]:
            model.update(truth_buildings(t, config, crs))
    else:
        from pipeline25d.formats.cityjson_buildings import cityjson_buildings

        for name in src["districts"]:
            spec = config["inputs"][name]
            model.update(cityjson_buildings(spec["path"], crs, spec.get("crs"), spec.get("lod"),
                                            spec.get("offset")))
    return [b.footprint for b in model.values() if b.footprint is not None], model


def reference_heights(p: dict, config: dict, fps: list[Footprint], model: dict[str, RefBuilding], ground: Sampler,
                      dsm_path: str | Path | None, gsd: float) -> tuple[dict[str, RefBuilding], str, str]:
    """The buildings' model roofs (and own ground) for the comparison, a sentence saying which, and
    its kind (truth, cityjson, obj, csv, dsm or none)."""
    ref = p["reference"]
    ids = {f.id for f in fps}
    if ref["source"] == "none":
        return {}, "none (heights.reference: none)", "none"
    if ref["source"] == "csv":
        from pipeline25d.analysis.heights.reference import read_reference

        # given as heights on the maps' basis: roof z = height + the DTM under the outline
        given = read_reference(ref["path"])
        fp_by = {f.id: f for f in fps}
        return ({k: RefBuilding(None, h + dtm_under(fp_by[k], ground, gsd)) for k, h in given.items() if k in fp_by},
                f"CSV {ref['path']} (heights taken as above the maps' DTM)", "csv")
    if ref["source"] == "obj":
        return obj_roofs(ref["path"]), f"OBJ {ref['path']} (roof material Building)", "obj"
    # auto
    if model and any(np.isfinite(b.roof_z) for b in model.values()):
        kind = p["footprints"]["source"]
        what = ("the generator's truth.json (exact)" if kind == "truth"
                else "the CityJSON buildings' roofs (RoofSurface or upward surfaces, mean z by area seen from above)")
        return model, what, kind
    for name in _inputs_of(config, "obj", (".obj",)):
        spec = config["inputs"][name]
        roofs = obj_roofs(spec["path"], float((spec.get("offset") or [0, 0, 0])[2]))
        if ids & set(roofs):
            return roofs, f"OBJ input {name} ({spec['path']}): roof material Building, per object", "obj"
    if dsm_path is None:
        return {}, "none (no model heights for these footprints)", "none"
    from pipeline25d.core.raster import DTM

    dsm = DTM(dsm_path, config["crs"])
    cell = abs(dsm.grid.res)
    return ({f.id: RefBuilding(None, dsm_roof(f, dsm.sample, cell)) for f in fps},
            f"the model's DSM ({dsm_path}, {cell:g} m cells): median inside each footprint, one cell in", "dsm")


def buildings_on_maps(p: dict, config: dict, nadir_map: str | Path) -> tuple[list[Footprint], list[Footprint],
                                                                           dict[str, RefBuilding]]:
    """(every footprint given, those inside the nadir map's extent, the model's buildings)."""
    fps_all, model = load_buildings(p, config)
    ext = _nadir_extent(nadir_map)
    return fps_all, [f for f in fps_all if _within(f.bounds, ext)], model


def settings_of(config: dict) -> MatchSettings:
    """The matcher's settings the config asks for."""
    h = config.get("heights") or {}
    return MatchSettings(max_height=float(h.get("max_height", MatchSettings.max_height)))


def write_skipped(reason: str, out_csv: str | Path, out_json: str | Path) -> dict[str, Any]:
    """The outputs of a skipped heights step (the reason in the JSON)."""
    from pipeline25d.core.atomic import write_json, write_text

    write_text(out_csv, "id,height\n")
    stats = {"skipped": reason}
    write_json(out_json, stats)
    log.info("heights skipped: %s", reason)
    return stats


def finish_stage(config: dict, p: dict, scene: Scene, rows: list, buildings: tuple, dsm_path: str | Path | None,
                 out_csv: str | Path, out_json: str | Path, cost: dict[str, Any]) -> dict[str, Any]:
    """Compare the measured ``rows`` with the model's heights (on the maps' basis, see the module
    docstring), write the CSV and the statistics JSON. ``buildings``: :func:`buildings_on_maps`;
    ``cost``: how the rows were measured (``job_seconds``: measuring time summed over jobs)."""
    from pipeline25d.analysis.heights.results import write_csv
    from pipeline25d.core.atomic import write_json

    fps_all, fps, model = buildings
    ground = ground_sampler(scene, config["crs"])
    gsd = float(config["gsd"])
    s = settings_of(config)
    views = sorted({k for r in rows for k in r.heights})
    refs, ref_source, ref_kind = reference_heights(p, config, fps, model, ground, dsm_path, gsd)

    fp_by = {f.id: f for f in fps}
    base = {k: dtm_under(fp_by[k], ground, gsd) for k in refs if k in fp_by}
    eave = {k: refs[k].roof_z - base[k] for k in base}
    ridge = {k: refs[k].ridge_z - base[k] for k in base if refs[k].kind in PITCHED}
    span = {k: ground_range_under(fp_by[k], ground, gsd) for k in base}
    own = {k: refs[k].roof_z - refs[k].own_ground_z for k in base if np.isfinite(refs[k].own_ground_z)}
    kinds = {k: refs[k].kind for k in base}
    gabled = {k for k, v in kinds.items() if v in PITCHED}
    groups: dict[str, Any] = {}
    if gabled:
        groups["flat"] = group_stats(rows, {k: v for k, v in eave.items() if k not in gabled}, views)
        for kind in PITCHED:
            ids = [k for k in gabled if kinds[k] == kind]
            if ids:
                groups[f"{kind}_eave"] = group_stats(rows, {k: eave[k] for k in ids}, views)
                groups[f"{kind}_ridge"] = group_stats(rows, {k: ridge[k] for k in ids}, views, ridge=True)
    elif eave:
        groups["all"] = group_stats(rows, eave, views)
    main = "flat" if gabled else "all"
    own_stats = (group_stats(rows, {k: v for k, v in own.items() if k not in gabled}, views)
                 if own and main in groups else None)
    reasons: dict[str, dict[str, int]] = {}
    for v in views:
        for r in rows:
            why = r.reasons.get(v, "missing") or "measured"
            reasons.setdefault(v, {})[why] = reasons.setdefault(v, {}).get(why, 0) + 1
    fmt = lambda x: "" if not np.isfinite(x) else f"{x:.3f}"  # noqa: E731
    extra = {"reference": {k: fmt(v) for k, v in eave.items()},
             "reference_ridge": {k: fmt(v) for k, v in ridge.items()},
             "roof": {k: v for k, v in kinds.items()},
             "ridge": {r.id: fmt(r.ridge) for r in rows},
             "roof_measured": {r.id: r.roof for r in rows},
             "reference_above_lowest": {k: fmt(refs[k].roof_z - span[k][0]) for k in base},
             "reference_above_highest": {k: fmt(refs[k].roof_z - span[k][1]) for k in base},
             "ground_under": {k: fmt(v) for k, v in base.items()}}
    write_csv(out_csv, rows, extra)
    stats = {
        "footprints": {**{k: v for k, v in p["footprints"].items()}, "n_given": len(fps_all), "n_on_maps": len(fps)},
        "n_measured": sum(1 for r in rows if np.isfinite(r.height)),
        "views": views, "reasons": reasons,
        "reference": {"source": ref_source, "kind": ref_kind, "n": len(base),
                      "main_group": main if main in groups else None,
                      "basis": (BASIS + ": "
                                + (f"DTM {scene.dtm}" if scene.dtm else f"the plane z0 = {scene.z0} m"))},
        "groups": groups,
        "own_ground": own_stats,
        "own_ground_source": OWN_GROUND.get(ref_kind) if own_stats else None,
        "settings": dict(s.__dict__),
        "cost": {**cost, **{f"{k}_per_1000_building_views": (round(1000 * cost[k] / (len(fps) * len(views)), 1)
                                                              if fps and views else None)
                            for k in ("job_seconds", "job_cpu_seconds") if k in cost}},
    }
    write_json(out_json, stats)
    return stats
