"""Kill-safe resume: runs interrupted by SIGKILL, SIGINT and SIGTERM resume to byte-identical outputs."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from pipeline25d_lab.harness.killtest import demo_config, differences, live_members, output_digests, run_trials


def test_digests_cover_maps_and_web_tiles_and_differences_name_each_path(tmp_path):
    (tmp_path / "maps").mkdir()
    (tmp_path / "tms" / "a" / "16" / "1").mkdir(parents=True)
    (tmp_path / "maps" / "a.tif").write_bytes(b"map")
    (tmp_path / "maps" / "a.json").write_text("{}")            # not an output compared
    (tmp_path / "tms" / "a" / "16" / "1" / "2.webp").write_bytes(b"tile")
    got = output_digests(tmp_path)
    assert sorted(got) == ["maps/a.tif", "tms/a/16/1/2.webp"]
    want = {**got, "maps/a.tif": "0" * 64, "maps/b.tif": "1" * 64}
    assert differences(got, want) == ["maps/a.tif", "maps/b.tif"]
    assert differences(got, got) == []


def test_live_members_sees_a_process_group_until_it_is_gone():
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)
    try:
        assert live_members(proc.pid) == [proc.pid]
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert live_members(proc.pid) == []


HANG_S = 60.0     # a run still going this long after SIGINT/SIGTERM hangs


@pytest.mark.slow
def test_runs_killed_interrupted_and_terminated_resume_to_identical_maps_and_tiles(tmp_path):
    """Three trials on a small demo city, one per signal; make killtest runs twenty and reports how
    long each run took to stop. Here the limit only tells a stop from a hang: on a loaded 2-core
    machine Snakemake took over 10 s to wind down after SIGTERM (twice in many runs)."""
    config = demo_config(tmp_path / "scene", 0.25, [{"azimuth": 45, "elevation": 45},
                                                    {"azimuth": 225, "elevation": 45}])
    result = run_trials(tmp_path / "work", config, 3, ["KILL", "INT", "TERM"], seed=3, stop_limit=HANG_S)
    assert result["files_compared"] > 10
    for rec in result["trials"]:
        assert rec["ok"] and rec["identical"] and rec["resume_rc"] == 0, rec
        assert not rec["finished_before_signal"], rec          # the signal came while it ran
        if rec["signal"] != "KILL":
            assert rec["stopped"] and rec["stop_s"] < HANG_S, rec


def test_a_trial_that_did_not_resume_identical_names_the_jobs_each_run_started(tmp_path):
    """What a failed trial's message carries (CI keeps nothing else): the jobs the interrupted run
    started and the resumed run ran, with their wildcards, and the interrupted run's last lines."""
    from pipeline25d_lab.harness.killtest import what_ran

    (tmp_path / "interrupted.log").write_text(
        "Select jobs to execute...\n\nlocalrule ingest:\n    input: a.obj\n    wildcards: district=d1\n\n"
        "localrule terrain:\n    output: t.tif\n\nlocalcheckpoint plan:\n    wildcards: pid=az045_el45\n")
    (tmp_path / "resumed.log").write_text("rule warp:\n    wildcards: pid=az045_el45\n")
    got = what_ran(tmp_path)
    assert got["interrupted_jobs"] == ["ingest (district=d1)", "terrain", "plan (pid=az045_el45)"]
    assert got["resumed_jobs"] == ["warp (pid=az045_el45)"]
    assert got["interrupted_tail"][-1] == "    wildcards: pid=az045_el45"
