"""The package as a newcomer meets it: small modules (or a stated reason), and an installed copy that works.

The layer rules themselves are import-linter contracts (pyproject.toml), checked by
``lint-imports`` in ``make test`` before the suite.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO

MAX_LINES = 400


def test_no_module_over_400_lines_without_a_reason_in_its_docstring():
    long = []
    for path in sorted((REPO / "src").rglob("*.py")):
        text = path.read_text()
        if text.count("\n") > MAX_LINES and "Over 400 lines" not in (ast.get_docstring(ast.parse(text)) or ""):
            long.append(f"{path.relative_to(REPO)}: {text.count(chr(10))} lines")
    assert not long, long


def test_every_module_has_a_docstring():
    missing = [str(p.relative_to(REPO)) for p in (REPO / "src").rglob("*.py")
               if p.name != "__main__.py" and not ast.get_docstring(ast.parse(p.read_text()))]
    assert not missing, missing


@pytest.mark.slow
def test_an_installed_copy_runs_from_anywhere(tmp_path):
    """``pip install .`` (dependencies from this venv): the CLI, its lab commands, the shaders and the
    viewer's files come with the package, and ``pipeline25d run config/config.yaml --dry-run`` works
    in the checkout."""
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--target", str(target), str(REPO)], check=True, capture_output=True)
    assert not (target / "pipeline25d" / "__init__.py").samefile(REPO / "src" / "pipeline25d" / "__init__.py")
    env = {**os.environ, "PYTHONPATH": str(target)}
    probe = ("import pipeline25d, pipeline25d.stages.render as r, pipeline25d.publish.viewer as v; "
             "print(pipeline25d.__file__); assert '#version 330' in r.VERTEX_SHADER; assert v.TEMPLATE.is_file()")
    out = subprocess.run([sys.executable, "-c", probe], env=env, cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().startswith(str(target))
    helped = subprocess.run([sys.executable, "-m", "pipeline25d", "--help"], env=env, cwd=tmp_path,
                            capture_output=True, text=True)
    assert helped.returncode == 0 and "demo" in helped.stdout and "sample" in helped.stdout
    config = yaml_demo_config(tmp_path)
    dry = subprocess.run([sys.executable, "-m", "pipeline25d", "run", str(config), "--dry-run", "--directory",
                          str(tmp_path)], env=env, cwd=REPO, capture_output=True, text=True)
    assert dry.returncode == 0, dry.stderr[-2000:]
    assert "render_block" in dry.stdout or "plan" in dry.stdout


def yaml_demo_config(tmp_path: Path) -> Path:
    """config/config.yaml on a small demo city generated in ``tmp_path``."""
    import yaml

    from pipeline25d_lab.scenes.demo import generate_demo_city

    generate_demo_city(tmp_path / "resources" / "demo", seed=3, n_buildings=10, scale=0.3)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump({**config, "scene": "installed"}))
    return path
