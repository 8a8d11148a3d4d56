"""Configuration: schema validation with defaults, then checks the schema cannot express.

Both run before any job, so a bad config stops the run with a message naming the key
or file, and nothing is written.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from pipeline25d.core.crs import check_scene_crs, parse_crs, transformer
from pipeline25d.core.errors import ConfigError, CRSError, InputFileError
from pipeline25d.geometry.perspectives import Perspective, expand
from pipeline25d.geometry.sun import check_sun_config

# the schema of the checkout this package lives in (an installed copy passes its workflow's own)
SCHEMA_PATH = Path(__file__).resolve().parents[2] / "config" / "schema.yaml"


def validate_schema(config: dict[str, Any], schema_path: Path = SCHEMA_PATH) -> dict[str, Any]:
    """Validate ``config`` in place against the JSON schema, filling defaults.

    Uses Snakemake's validator (the same one the Snakefile calls); raises ConfigError
    with the offending key path.
    """
    import jsonschema
    from snakemake.utils import validate

    try:
        validate(config, str(schema_path), set_default=True)
    except Exception as exc:  # WorkflowError wrapping jsonschema.ValidationError
        cause = exc.__cause__ or exc.__context__ or exc
        if isinstance(cause, jsonschema.ValidationError):
            if cause.context:  # oneOf/anyOf: report the most relevant branch's error
                cause = max(cause.context, key=lambda e: (len(e.absolute_path), e.validator != "type"))
            key = ".".join(str(p) for p in cause.absolute_path) or "<top level>"
            raise ConfigError(f"config key {key}: {cause.message}") from None
        raise ConfigError(f"config is invalid: {exc}") from None
    return config


def check_semantics(config: dict[str, Any], base_dir: Path = Path(".")) -> None:
    """Checks beyond the schema: CRSs exist, the scene CRS is projected and every input's CRS
    transforms to it; input files exist and are files; an input's ``side_folders`` are folders."""
    try:
        check_scene_crs(config["crs"])
    except CRSError as exc:
        raise ConfigError(f"config key crs: {exc}") from None
    for name, spec in config["inputs"].items():
        if "crs" in spec:
            try:
                parse_crs(spec["crs"])
                transformer(spec["crs"], config["crs"])
            except CRSError as exc:
                raise ConfigError(f"config key inputs.{name}.crs ({spec['path']}): {exc}") from None
        for key in ("path", "metadata"):
            if key in spec:
                _check_readable(base_dir / spec[key], f"inputs.{name}.{key}", dataset_ok=key == "path")
        for k, folder in enumerate(spec.get("side_folders") or []):
            if not (base_dir / folder).is_dir():
                raise ConfigError(f"config key inputs.{name}.side_folders.{k}: {base_dir / folder} is not a folder")
    for key, value in (("terrain", config["terrain"]), ("gcp.source", config["gcp"]["source"])):
        if value not in ("auto", "flat"):
            _check_readable(base_dir / value, key)
    if config["terrain"] not in ("auto", "flat"):
        _check_raster(base_dir / config["terrain"], "terrain")
    zoom = config.get("tms", {}).get("zoom", "auto")
    if zoom != "auto" and "-" in zoom and int(zoom.split("-")[0]) > int(zoom.split("-")[1]):
        raise ConfigError(f"config key tms.zoom: {zoom} runs from a finer to a coarser level; write it low-high")
    check_sun_config(config.get("shadows", {}))
    for k, overlay in enumerate((config.get("viewer") or {}).get("overlays") or []):
        _check_readable(base_dir / overlay["path"], f"viewer.overlays.{k}.path")
        if "crs" in overlay:
            try:
                parse_crs(overlay["crs"])
            except CRSError as exc:
                raise ConfigError(f"config key viewer.overlays.{k}.crs ({overlay['path']}): {exc}") from None
    heights = config.get("heights") or {}
    for key in ("footprints", "reference"):
        if heights.get(key, "auto") not in ("auto", "none"):
            _check_readable(base_dir / heights[key], f"heights.{key}")


def objects_enabled(config: dict[str, Any]) -> bool:
    """``objects.enabled`` with ``auto`` resolved: on where any input names objects to identify
    (:func:`~pipeline25d.formats.has_objects.input_has_objects`), off for a scene of surfaces
    alone (PLY, OSGB photogrammetry, a tileset without feature ids)."""
    enabled = config["objects"]["enabled"]
    if enabled != "auto":
        return bool(enabled)
    from pipeline25d.formats.has_objects import input_has_objects

    return any(input_has_objects(spec) for spec in config["inputs"].values())


#: the ``gcp`` settings of the GCP marker pass, part of every tile's render settings; they change
#: what a tile observes, not its image (:func:`pipeline25d.stages.plan.image_hash`)
MARKER_SETTINGS = ("marker_px", "depth_bias", "max_float_px")


def render_settings(config: dict[str, Any]) -> dict[str, Any]:
    """What changes a tile's pixels (the render block size does not): the render and marker
    settings, and the ``shadows`` block only when shadows are enabled, so a config without
    shadows plans and renders exactly as before they existed."""
    out = {**{k: v for k, v in config["render"].items() if k != "block"},
           **{k: config["gcp"][k] for k in MARKER_SETTINGS}}
    shadows = config.get("shadows", {})
    if shadows.get("enabled"):
        out["shadows"] = {k: v for k, v in shadows.items() if k != "enabled"}
    return out


def _check_readable(path: Path, key: str, dataset_ok: bool = False) -> None:
    """``path`` exists, is readable and not empty; a folder only where ``dataset_ok`` and it is an
    OSGB dataset (holds Data/)."""
    if not path.exists():
        raise InputFileError(path, f"does not exist (config key {key})")
    from pipeline25d.formats import is_osgb_dataset

    if path.is_dir() and not (dataset_ok and is_osgb_dataset(path)):
        more = "; an OSGB dataset folder holds Data/" if dataset_ok else ""
        raise InputFileError(path, f"is a directory, not a file (config key {key}){more}")
    if not os.access(path, os.R_OK):
        raise InputFileError(path, f"is not readable (config key {key})")
    if path.is_file() and path.stat().st_size == 0:
        raise InputFileError(path, f"is empty (config key {key})")


def _check_raster(path: Path, key: str) -> None:
    """``path`` opens as a one-band raster (its header only: cheap at parse time)."""
    from pipeline25d.core.raster import gdal

    try:
        ds = gdal().Open(str(path))
    except RuntimeError as exc:
        raise InputFileError(path, f"cannot open as a raster (config key {key}): {exc}") from None
    if ds is None or ds.RasterCount < 1:
        raise InputFileError(path, f"holds no raster band (config key {key}); a DTM is a one-band GeoTIFF")


def load_config(path: str | Path, base_dir: Path = Path("."), schema_path: Path = SCHEMA_PATH) -> dict[str, Any]:
    """Read, validate and check a YAML config file (for the CLI and tests); its input paths are
    relative to ``base_dir``; ``schema_path``: the schema of the workflow that will run it."""
    path = Path(path)
    try:
        config = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read config: {exc}") from None
    if not isinstance(config, dict):
        raise ConfigError(f"{path}: config must be a mapping")
    validate_schema(config, schema_path)
    check_semantics(config, base_dir)
    return config


def perspectives(config: dict[str, Any]) -> list[Perspective]:
    """The validated config's perspectives."""
    return expand(config["perspectives"])


CHUNK_PX = 400          # chunk_size auto: a chunk spans this many map pixels ...
MIN_CHUNK_M = 100.0     # ... and at least this many metres


def chunk_size(config: dict[str, Any]) -> float:
    """The chunk edge in metres: the configured one, or auto = max(100 m, 400·gsd)."""
    value = config.get("chunk_size", "auto")
    return max(MIN_CHUNK_M, CHUNK_PX * float(config["gsd"])) if value == "auto" else float(value)
