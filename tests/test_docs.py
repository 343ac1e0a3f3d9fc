"""The project documents itself: a short README whose commands work, links that resolve, no reference outside."""

import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: Largest README, bytes.
README_MAX_BYTES = 8000
#: References to material outside the repository (the development notes it was built from), written in parts so
#: that this file does not match itself.
OUTSIDE = re.compile("|".join(["sha" + "red/", "DESIGN" + " section", "issue" + " [0-9]"]))
#: Files searched for such references: every text file of the project (binary files and caches skipped).
TEXT_SUFFIXES = {".py", ".md", ".toml", ".json", ".txt", ".cfg", ".ini", ".yml", ".yaml", ".html", ".sh", ""}


def _project_files():
    """The files git tracks (staged ones included); without git, every file outside caches, build output and
    virtual environments (a folder with a ``pyvenv.cfg``), which a user may well create inside the checkout."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
        paths = [REPO / name for name in listed.decode("utf-8").split("\0") if name]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", "__pycache__", ".pytest_cache", "results", "build", "dist"}
        venvs = [c.parent for c in REPO.rglob("pyvenv.cfg")]
        paths = [p for p in REPO.rglob("*") if not (set(p.relative_to(REPO).parts) & skip)
                 and "egg-info" not in str(p) and not any(v in p.parents for v in venvs)]
    for p in paths:
        if p.is_file() and p.suffix in TEXT_SUFFIXES:
            yield p


def test_no_file_points_outside_the_repository():
    hits = []
    for p in _project_files():
        try:
            text = p.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for i, line in enumerate(text.splitlines(), 1):
            if OUTSIDE.search(line):
                hits.append(f"{p.relative_to(REPO)}:{i}: {line.strip()[:100]}")
    assert not hits, "\n".join(hits)


def test_readme_is_short_and_has_the_two_set_up_commands():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    assert len(text.encode("utf-8")) < README_MAX_BYTES
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
    assert blocks[0].strip() == 'python -m pip install -e ".[rotorpy]" && pinnmpc run'
    assert blocks[1].strip() == 'python -m pip install -e ".[test]" && python -m pytest -n 2 --dist loadfile'
    # CI runs the README's test command, then the slower checks it leaves out
    ci = [ln.strip() for ln in (REPO / ".ci" / "run").read_text().splitlines() if ln.strip()]
    assert ci[-2:] == [blocks[1].strip(), "python -m pytest -m slow -n 2 --dist loadfile"]


def test_every_relative_link_of_the_docs_resolves():
    bad = []
    for p in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", p.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+://", target):
                continue
            if not (p.parent / target).exists():
                bad.append(f"{p.relative_to(REPO)} -> {target}")
    assert not bad, bad


def _quickstart() -> list[list[str]]:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    body = text.split("## Quickstart", 1)[1]
    block = re.findall(r"```bash\n(.*?)```", body, re.S)[0]
    return [line.split()[1:] for line in block.strip().splitlines()]


def test_the_readme_quickstart_runs(tmp_path, monkeypatch, capsys):
    import shutil

    from scenarios.cli import main

    cmds = _quickstart()
    assert 1 <= len(cmds) <= 5 and all(c[0] in ("check-model", "fly") for c in cmds)
    shutil.copytree(REPO / "models", tmp_path / "models")       # the commands use paths relative to the clone
    monkeypatch.chdir(tmp_path)
    for argv in cmds:
        assert main(argv) == 0, argv
        out = capsys.readouterr().out
        if argv[0] == "fly":
            assert re.search(r"^rmse_position_m\s+\S+", out, re.M), out
    assert (tmp_path / "fig8.png").read_bytes()[:4] == b"\x89PNG"
