"""The whole workflow through the SLURM profile on a one-node local cluster equals a -j2 run."""

from __future__ import annotations

import pytest

from pipeline25d.core.errors import ClusterError
from pipeline25d_lab.harness import slurm_cluster
from pipeline25d_lab.harness.killtest import demo_config
from pipeline25d_lab.harness.slurm_cluster import local_against_slurm, local_cluster, logged_counts, missing

TWO_VIEWS = [{"azimuth": 45, "elevation": 45}, {"azimuth": 0, "elevation": 90}]


def needs_cluster() -> None:
    if lacks := missing():
        pytest.skip("a local SLURM cluster needs " + ", ".join(lacks) + " (make sysdeps installs the packages)")


def test_logged_counts_are_the_last_step_total_the_local_rules_and_the_submissions(tmp_path):
    log = tmp_path / "snakemake.log"
    log.write_text("Job 3 has been submitted with SLURM jobid 1 (log: a)\n1 of 3 steps (33%) done\n"
                   "Job 4 has been submitted with SLURM jobid 2 (log: b)\n2 of 4 steps (50%) done\n"
                   "localrule all:\n    input: x\n4 of 4 steps (100%) done\n")
    assert logged_counts(log) == {"jobs": 4, "local_jobs": 1, "submissions_logged": 2}


def test_a_daemon_that_exits_at_start_is_named_with_its_log_and_nothing_is_left(tmp_path, monkeypatch):
    needs_cluster()
    monkeypatch.setitem(slurm_cluster.DAEMONS, "slurmd", "/bin/false")
    with pytest.raises(ClusterError, match=f"slurmd exited with status 1 at start; see {tmp_path}/log/slurmd.log"):
        with local_cluster(tmp_path):
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log", "slurm.conf"]


@pytest.mark.slow
def test_slurm_run_is_byte_identical_to_a_local_run_with_fewer_submissions_than_jobs(tmp_path):
    needs_cluster()
    result = local_against_slurm(tmp_path, demo_config(tmp_path / "scene", 0.25, TWO_VIEWS))
    assert result["identical"], result["differing"]
    # every submission the cluster saw is one Snakemake logged, and grouping made them fewer than the jobs
    assert result["slurm_submissions"] == result["submissions_logged"] > 0
    assert result["slurm_submissions"] < result["remote_jobs"] < result["jobs"]
