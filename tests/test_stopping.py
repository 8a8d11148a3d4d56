"""A stop signal ends a job as failed even where a library caught the exception it raised.

trimesh's OBJ reader wraps its material and texture loading in ``except BaseException``. A
SIGTERM that arrived there returned the mesh untextured, and the job wrote it as a finished chunk
(a kill trial of test_killtest resumed to different maps). These tests deliver the signal exactly
there, in a job process set up as the workflow's are.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

SCRIPT = textwrap.dedent("""
    import os, signal, sys
    import PIL.Image, trimesh
    from pipeline25d.core.logsetup import log_to
    from pipeline25d.core.atomic import write_bytes

    folder, sig = sys.argv[1], getattr(signal, sys.argv[2])
    signal.signal(signal.SIGINT, signal.default_int_handler)    # as from a terminal, whoever started pytest
    log_to(os.path.join(folder, "job.log"))
    opened = PIL.Image.open

    def open_and_stop(*args, **kwargs):          # the cancel arrives while the texture loads
        os.kill(os.getpid(), sig)
        return opened(*args, **kwargs)

    PIL.Image.open = open_and_stop
    mesh = trimesh.load(os.path.join(folder, "quad.obj"), process=False)
    image = getattr(getattr(mesh.visual, "material", None), "image", None)
    print("read", "with its texture" if image is not None else "without its texture", flush=True)
    write_bytes(os.path.join(folder, "chunk.npz"), b"a chunk drawn from that mesh")
    print("wrote", flush=True)
""")


def _textured_quad(folder: Path) -> None:
    Image.fromarray(np.full((4, 4, 3), 200, np.uint8)).save(folder / "tex.png")
    (folder / "quad.mtl").write_text("newmtl m\nmap_Kd tex.png\n")
    (folder / "quad.obj").write_text("mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
                                     "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")


@pytest.mark.parametrize("name", ["SIGTERM", "SIGINT"])
def test_a_signal_a_library_swallowed_still_stops_the_job_before_its_output(tmp_path, name):
    _textured_quad(tmp_path)
    sig = getattr(signal, name)
    run = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path), name], capture_output=True, text=True,
                         timeout=120)
    # the mechanism: trimesh dropped the signal's exception and returned the quad without its texture
    assert "read without its texture" in run.stdout, (run.stdout, run.stderr)
    assert run.returncode == 128 + sig, run.stderr
    assert "wrote" not in run.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["job.log", "quad.mtl", "quad.obj", "tex.png"]


def test_a_job_whose_function_swallowed_a_signal_fails_after_it(tmp_path):
    """Through the workflow's one seam (``jobs.run``): a rule function that catches the SIGTERM and
    returns normally still ends its job with status 143, without its resources line (a finished
    job's last)."""
    script = textwrap.dedent("""
        import os, signal, sys, time, types
        from pipeline25d import jobs

        def swallow(job):
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)
            except BaseException:
                pass

        jobs.RULES["swallow"] = swallow
        jobs.run(types.SimpleNamespace(rule="swallow", log=[sys.argv[1]], threads=1))
        print("returned", flush=True)
    """)
    log = tmp_path / "job.log"
    run = subprocess.run([sys.executable, "-c", script, str(log)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 143, run.stderr
    assert "returned" not in run.stdout
    assert "job resources" not in log.read_text()


def test_without_a_signal_the_same_job_writes_its_output(tmp_path):
    """The control: the same script whose texture loads without a signal writes its output."""
    _textured_quad(tmp_path)
    script = SCRIPT.replace("os.kill(os.getpid(), sig)", "pass")
    run = subprocess.run([sys.executable, "-c", script, str(tmp_path), "SIGTERM"], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    assert "read with its texture" in run.stdout and "wrote" in run.stdout
    assert (tmp_path / "chunk.npz").read_bytes() == b"a chunk drawn from that mesh"



def test_a_forked_worker_dies_on_a_signal_rather_than_hand_back_a_result():
    """A job's forked worker (``fork_pool``) that takes the signal inside a library that drops it
    is ended by it: the job fails on the broken pool instead of writing the worker's result."""
    script = textwrap.dedent("""
        import os, signal, time
        from pipeline25d.core.cores import fork_pool
        from pipeline25d.core.stopping import remember_stop_signals

        def swallow():
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)
            except BaseException:
                pass
            return "a result drawn after the signal"

        remember_stop_signals()                   # as log_to sets up every job
        with fork_pool(1) as pool:
            print(pool.submit(swallow).result(timeout=60), flush=True)
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "BrokenProcessPool" in run.stderr, (run.stdout, run.stderr)
    assert "a result" not in run.stdout
