"""Two runs at once in one checkout: two scenes do not interfere; a second run of the same scene is refused."""

from __future__ import annotations

import subprocess
import time

import pytest
import yaml

from pipeline25d.core.atomic import write_text
from pipeline25d_lab.harness.bench import results_of, run_workflow, workflow_command
from pipeline25d_lab.harness.killtest import demo_config, output_digests

ONE_VIEW = [{"azimuth": 45, "elevation": 45}]


@pytest.mark.slow
def test_two_scenes_run_side_by_side_and_the_same_scene_twice_is_refused(tmp_path):
    base = demo_config(tmp_path / "scene", 0.25, ONE_VIEW)
    configs = {name: {**base, "scene": name} for name in ("north", "south")}
    work = tmp_path / "checkout"
    work.mkdir()
    for name, config in configs.items():
        write_text(work / f"{name}.yaml", yaml.safe_dump(config))
    first = subprocess.Popen(workflow_command(work, 1, work / "north.yaml"), stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    locks = work / ".snakemake" / "locks"
    while first.poll() is None and not (locks.is_dir() and any(locks.iterdir())):
        time.sleep(0.1)
    assert first.poll() is None, "the first run ended before a second could start beside it"
    again = subprocess.run(workflow_command(work, 1, work / "north.yaml"), capture_output=True, text=True)
    other = subprocess.run(workflow_command(work, 1, work / "south.yaml"), capture_output=True, text=True)
    out, _ = first.communicate()
    assert first.returncode == 0, out[-2000:]
    assert again.returncode != 0 and "cannot be locked" in again.stdout + again.stderr
    assert other.returncode == 0, (other.stdout + other.stderr)[-2000:]
    # the scene run beside another equals the same scene run alone
    run_workflow(tmp_path / "alone", configs["south"], cores=1)
    beside = output_digests(results_of(work, configs["south"]))
    assert beside and beside == output_digests(results_of(tmp_path / "alone", configs["south"]))
