"""A job's description (pipeline25d.jobspec): what a rule's command hands on reads back as Snakemake's
own job object read; its file is named by what it holds; the command runs it with a host and without."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from snakemake.iocontainers import InputFiles, OutputFiles

from pipeline25d import jobhost, jobspec
from pipeline25d.core.errors import Pipeline25dError


def _named(cls, groups: list[tuple[str | None, str | list[str]]]):
    """Snakemake's list of files with named entries, as a rule's ``input:`` or ``output:`` makes it."""
    files = cls()
    for name, value in groups:
        start = len(files)
        if isinstance(value, list):
            files.extend(value)
            if name:
                files._set_name(name, start, len(files))
        else:
            files.append(value)
            if name:
                files._set_name(name, start)
    return files


def test_a_job_reads_back_as_snakemake_s_job_object_read(tmp_path):
    snake_in = _named(InputFiles, [("cog", "maps/a.tif"), ("maps", ["m1.tif", "m2.tif"]), (None, "loose.json"),
                                   ("empty", [])])
    snake_out = _named(OutputFiles, [("index", "chunks/index.json"), ("lod", "lod/index.json")])
    params = {"gsd": 0.25, "spec": {"path": "d.ply", "crs": "EPSG:28992"}, "pids": ["az000_el90"], "flag": None}
    path = jobspec.write(tmp_path, jobspec.encode(snake_in, snake_out, params, {"district": "d01-02"}))
    job = jobspec.load("ingest", "2", path, "logs/x.log")

    assert job.rule == "ingest" and job.threads == 2 and job.log == ["logs/x.log"]
    assert list(job.input) == [str(f) for f in snake_in]
    assert job.input.cog == snake_in.cog == "maps/a.tif"
    assert job.input.maps == list(snake_in.maps) and job.input.empty == []
    # a name hides the list method it shares (output.index), on both
    assert job.output.index == snake_out.index == "chunks/index.json" and job.output[1] == "lod/index.json"
    assert not hasattr(job.output, "ids") and not hasattr(snake_out, "ids")
    assert vars(job.params) == params and job.wildcards.district == "d01-02"


def test_a_job_s_file_is_named_by_what_it_holds(tmp_path):
    out = _named(OutputFiles, [("map", "maps/a.tif")])

    def path(**params) -> str:
        return jobspec.write(tmp_path, jobspec.encode(InputFiles(), out, params, {"pid": "az045_el45"}))

    first = path(gsd=0.25)
    assert path(gsd=0.25) == first                             # written once, the same path each time
    assert path(gsd=0.5) != first                              # anything else: another file
    assert len(list(tmp_path.iterdir())) == 2
    assert json.loads(Path(first).read_text())["params"] == {"gsd": 0.25}


def test_a_job_whose_file_is_gone_says_so(tmp_path):
    with pytest.raises(Pipeline25dError, match="gone.json: the job's description cannot be read"):
        jobspec.load("tms", 1, tmp_path / "gone.json", "x.log")


@pytest.mark.parametrize("hosted", [False, True])
def test_a_rule_s_command_runs_its_job_with_a_host_and_without(tmp_path, hosted, request):
    """The command every rule runs (python -I -S jobhost.py job ...): the job's function runs on the
    host's fork or, without a host, in the process the command becomes; its log says which."""
    import tempfile

    from PIL import Image

    tile = tmp_path / "tms" / "14" / "8400" / "5390.png"
    tile.parent.mkdir(parents=True)
    Image.new("RGBA", (256, 256), (200, 100, 50, 255)).save(tile)
    archive = tmp_path / "out" / "az045_el45.pmtiles"
    out = _named(OutputFiles, [(None, str(archive))])
    inp = _named(InputFiles, [("tiles", str(tmp_path / "tms"))])
    spec = jobspec.write(tmp_path / "jobs", jobspec.encode(inp, out, {}, {"pid": "az045_el45"}))
    env = {k: v for k, v in os.environ.items() if k != jobhost.SOCKET_ENV}
    if hosted:
        env[jobhost.SOCKET_ENV] = request.getfixturevalue("host")
    log = tmp_path / "pmtiles.log"
    done = subprocess.run([sys.executable, "-I", "-S", jobhost.__file__, "job", "pmtiles", "1", spec, str(log)],
                          cwd=tempfile.gettempdir(), env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    from pmtiles.reader import MmapSource, Reader

    with open(archive, "rb") as f:
        reader = Reader(MmapSource(f))
        assert reader.metadata()["name"] == "az045_el45"          # the job's wildcard
        assert reader.get(14, 8400, 5390) == tile.read_bytes()
    assert ("job host" in log.read_text()) == hosted


def test_descriptions_unused_for_a_week_are_removed_and_used_ones_kept(tmp_path):
    out = _named(OutputFiles, [("map", "maps/a.tif")])
    old, used, fresh = (jobspec.write(tmp_path, jobspec.encode(InputFiles(), out, {"n": n}, {})) for n in range(3))
    week = jobspec.KEEP_UNUSED_S
    for path in (old, used):
        os.utime(path, (0, Path(path).stat().st_mtime - week - 60))
    assert jobspec.write(tmp_path, jobspec.encode(InputFiles(), out, {"n": 1}, {})) == used   # a run uses it again
    assert jobspec.prune(tmp_path) == 1
    assert not Path(old).exists() and Path(used).exists() and Path(fresh).exists()
