"""Every command the README shows works as written from the repository root, with no PATH set by hand.

Each command is checked as far as it can be without its inputs: programs are the venv's or
make, make targets dry-run (``make -n``), Snakemake and ``pipeline25d run`` commands dry-run
on their configs, and every ``pipeline25d`` command answers ``--help`` with every option the
README gives it.
``make run``/``make test`` themselves run in CI from a fresh clone (``.ci/run``).
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
#: the README and the docs pages it links: every command they show is checked alike
PAGES = [README, *(p.read_text() for p in sorted((REPO / "docs").glob("*.md")))]
PROGRAM = re.compile(r"(make|python3?|snakemake|pytest|pip)\b|\.venv/bin/")


def shown_commands(text: str) -> list[str]:
    """Command lines of a page's fenced shell blocks (comments dropped) and its inline commands."""
    commands = []
    for block in re.findall(r"```(?:bash|sh)?\n(.*?)```", text, re.S):
        for line in block.splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if line and not line.startswith("#"):
                commands.append(line)
    commands += [code for code in re.findall(r"`([^`\n]+)`", text) if PROGRAM.match(code)]
    return list(dict.fromkeys(commands))


COMMANDS = list(dict.fromkeys(c for page in PAGES for c in shown_commands(page)))


def test_the_readme_shows_the_commands_a_new_user_needs():
    assert shown_commands(README)[:2] == ["make run", "make test"]            # the first two, as the guide asks
    assert any(c.startswith(".venv/bin/snakemake") for c in COMMANDS)   # the engine, still usable directly
    assert any(c.startswith(".venv/bin/pipeline25d run ") for c in COMMANDS)


def test_the_readme_has_one_front_door():
    """No ``python -m pipeline25d…`` module commands: every tool is a ``pipeline25d`` command."""
    assert not any(re.search(r"python3? -m pipeline25d", page) for page in PAGES)


def test_the_readme_opens_with_pictures_of_the_output_that_exist():
    """Pictures before the quick start, each a file in the repository (``make pictures`` makes them)."""
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", README.split("```")[0])
    assert len(pictures) >= 2, "the README opens with pictures of the maps and the viewer"
    for picture in pictures:
        assert (REPO / picture).is_file(), picture
    assert "make pictures" in COMMANDS


def test_every_docs_page_is_linked_from_the_readme():
    for page in (REPO / "docs").glob("*.md"):
        assert f"docs/{page.name}" in README, page.name


@pytest.mark.parametrize("command", COMMANDS)
def test_no_command_relies_on_path(command):
    args = shlex.split(command)
    if args[0] == "python3" and args[1] == "-m":                # Debian's own Python: the standard library only
        assert args[2].split(".")[0] in sys.stdlib_module_names, f"{command!r} needs the venv's Python"
        return
    assert args[0] == "make" or args[0].startswith(".venv/bin/"), \
        f"{command!r} runs {args[0]!r} from PATH, which a fresh clone does not set up"


@pytest.mark.parametrize("command", [c for c in COMMANDS if c.startswith("make ")])
def test_make_targets_dry_run(command):
    proc = subprocess.run(shlex.split(command)[:1] + ["-n"] + shlex.split(command)[1:], cwd=REPO,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


#: README commands that generate an example's input under resources/: {folder: command}
GENERATORS = {m.group(1): c for c in COMMANDS
              if (m := re.fullmatch(r"\.venv/bin/pipeline25d (?:demo|sample \w+) (resources/[\w.-]+)", c))}


def _generate_inputs(configfile: Path) -> None:
    """Run, as the README shows it, the generator of every resources/ input (or overlay) the config lacks."""
    import yaml

    config = yaml.safe_load(configfile.read_text())
    overlays = (config.get("viewer") or {}).get("overlays") or []
    for spec in [*(config.get("inputs") or {}).values(), *overlays]:        # a generator writes both
        path = str(spec.get("path", ""))
        folder = "/".join(path.split("/")[:2])
        if path.startswith("resources/") and not (REPO / path).exists() and folder in GENERATORS:
            subprocess.run(shlex.split(GENERATORS[folder]), cwd=REPO, check=True, capture_output=True)


RUNS = [c for c in COMMANDS if c.startswith((".venv/bin/snakemake", ".venv/bin/pipeline25d run"))]


@pytest.mark.parametrize("command", RUNS)
def test_workflow_commands_dry_run(command):
    args = shlex.split(command)
    if "--unlock" in args:
        pytest.skip("--unlock only acts on a locked folder")
    configs = [args[k + 1] for k, arg in enumerate(args[:-1]) if arg == "--configfile"]
    if args[1] == "run":
        configs += [a for a in args[2:3] if a.endswith(".yaml")]
    for config in configs:
        assert (REPO / config).exists(), f"{config} is not in the repository"
        _generate_inputs(REPO / config)
    dry = ["-n", "--quiet"] if args[0].endswith("snakemake") else ["--dry-run", "--quiet"]
    proc = subprocess.run(args + dry, cwd=REPO, capture_output=True, text=True)
    if proc.returncode and "shared/data" in proc.stdout + proc.stderr and not (REPO.parent / "shared").exists():
        pytest.skip("the shared data are not beside this checkout")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-2000:]


@pytest.mark.parametrize("command", [c for c in COMMANDS if c.startswith(".venv/bin/pipeline25d ")])
def test_cli_commands_take_the_options_shown(command):
    args = shlex.split(command)
    words = []                                  # the command and its sub-commands: bare words up to the first path
    for arg in args[1:]:
        if not re.fullmatch(r"[a-z][a-z-]*", arg):
            break
        words.append(arg)
    proc = subprocess.run([args[0], *words, "--help"], cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    for option in (a.split("=")[0] for a in args if a.startswith("--")):
        assert option in proc.stdout, f"pipeline25d {' '.join(words)} has no option {option}"
