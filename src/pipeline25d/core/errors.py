"""Project exceptions: one base class, small named subclasses.

Callers catch :class:`Pipeline25dError`; tests assert the exact class. Each error
that concerns a file names the file, so the message alone tells a user what to fix.
"""

from __future__ import annotations


class Pipeline25dError(Exception):
    """Base class of every error raised on purpose by pipeline25d."""


class ConfigError(Pipeline25dError, ValueError):
    """The configuration is invalid (schema violation, unknown CRS, bad value)."""


class FileProblem(Pipeline25dError, OSError):
    """A problem with one file or folder; the message is "<path>: <problem>"."""

    def __init__(self, path: object, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class InputFileError(FileProblem):
    """An input file is missing, unreadable, truncated or corrupt."""


class UnsupportedFeatureError(InputFileError):
    """An input uses a feature pipeline25d cannot honour (e.g. a required glTF extension)."""


class OutputError(FileProblem):
    """An output cannot be written (no space left on the device, no permission); names the path."""


class MissingTextureWarning(UserWarning):
    """A model's texture is missing, not an image or undecodable; its parts would be drawn untextured.
    Ingest makes it an error unless the input says ``missing_textures: untextured``."""


class CRSError(Pipeline25dError, ValueError):
    """A CRS is unknown, not projected, or cannot be transformed to the scene CRS."""


class RenderError(Pipeline25dError, RuntimeError):
    """The OpenGL context could not be created or a render failed."""


class GroundError(Pipeline25dError, ValueError):
    """``terrain: auto`` found no ground (anywhere, or near part of the model); the message names
    the inputs and what to do (give a DTM, or terrain: flat)."""


class GdalToolError(Pipeline25dError, RuntimeError):
    """A GDAL command-line tool exited with an error."""


class WorkflowRunError(Pipeline25dError, RuntimeError):
    """A whole workflow run (Snakemake) failed; the message names its log."""


class ClusterError(Pipeline25dError, RuntimeError):
    """The local SLURM cluster (tests, benchmarks) did not start or stop; the message names the daemon and its log."""


class MapServiceError(Pipeline25dError, RuntimeError):
    """A map service (the WMS mapfile, MapServer) cannot be set up; the message names the file."""


class MeasureError(Pipeline25dError, ValueError):
    """A measurement on a map cannot be made (a nadir map, too few points, a facade seen edge-on)."""
