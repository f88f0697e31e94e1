"""Documentation that is generated from code stays in step with it, and every example in README.md
and docs/*.md runs as written.

Each document's Python and shell blocks run in order in a scratch folder that holds a copy of the
files git tracks (outputs of one block, e.g. a generated dataset, are inputs of a later one; nothing
a user generated in the clone, such as the README's `data/clouds`, leaks in).
Shell commands run as written with three adjustments: `pip install` steps are skipped (this suite
runs in the installed environment), `python -m pytest` is skipped (it is what runs this test), and
`torchvol` commands get small images through their documented overrides (SMALL) and generate at
most COUNT samples (`--count` given again: the last one counts). A block that
cannot run here is preceded by `<!-- not run: REASON -->`; it must still name only files the
repository ships, as must every block."""

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELL, PYTHON = ("bash", "sh", "shell", "console"), ("python", "py")
SMALL = {  # documented overrides that keep the examples quick
    "render": ["--set", "image.width=32", "--set", "image.height=24"],
    "generate": ["--set", "image.width=16", "--set", "image.height=12"],
    "sweep": ["--set", "image.width=24", "--set", "image.height=24"],
    "bench": ["--width", "16", "--height", "12", "--repeat", "1"],
}
COUNT = 64
NOT_RUN = re.compile(r"<!-- not run: (.+?) -->\s*$")


def blocks(path: Path) -> list[tuple[str, str, str | None]]:
    """(language, code, reason it is not run or None) of every fenced block of a Markdown file."""
    out, lines, n = [], path.read_text().splitlines(), 0
    while n < len(lines):
        fence = re.match(r"^(\s*)```(\w*)", lines[n])
        if not fence:
            n += 1
            continue
        indent, language, start = fence.group(1), fence.group(2), n
        body = []
        n += 1
        while not lines[n].startswith(indent + "```"):
            body.append(lines[n][len(indent):])
            n += 1
        reason = next((NOT_RUN.match(lines[k]).group(1) for k in range(start - 1, max(start - 3, -1), -1)
                       if NOT_RUN.match(lines[k])), None)
        out.append((language, "\n".join(body) + "\n", reason))
        n += 1
    return out


def shell_commands(code: str) -> list[str]:
    """A shell block as the commands to run: continuation lines joined, `pip install` and the test
    command dropped, small sizes added to `torchvol` commands."""
    commands = []
    for line in code.replace("\\\n", " ").splitlines():
        line = line.split(" #", 1)[0].strip()
        if not line or line.startswith("#"):
            continue
        kept = []
        for part in (p.strip() for p in line.split("&&")):
            words = shlex.split(part)
            if words[:2] == ["pip", "install"] or words[:3] == ["python", "-m", "pytest"]:
                continue
            if words[0] == "torchvol":
                part += " " + " ".join(SMALL.get(words[1], []))
                if "--count" in words and int(words[words.index("--count") + 1]) > COUNT:
                    part += f" --count {COUNT}"
            kept.append(part)
        if kept:
            commands.append(" && ".join(kept))
    return commands


def named_files(code: str) -> list[str]:
    """Scene, recipe and tool files a block names (inputs: they must ship with the repository)."""
    return [m for m in re.findall(r"[\w./-]+\.(?:toml|py)\b", code) if not m.startswith(("torchvol.", "tv."))]


# What the documents' commands read: the shipped files outside the package. The package itself is the
# installed one (the code under test, untracked new modules included), never a second copy in the scratch.
SHIPPED = ("README.md", "pyproject.toml", "datasets", "docs", "examples", "tools", "tests")
NOT_INPUTS = (".ci/", "torchvol/")


def tracked_files(root: Path = ROOT) -> list[str]:
    """Paths, relative to root, of the files git tracks there outside NOT_INPUTS; outside a git
    checkout (an unpacked archive), the files of the SHIPPED entries, without caches."""
    if in_git_checkout(root):
        listed = subprocess.run(["git", "-C", str(root), "ls-files", "-z"], capture_output=True, text=True, check=True)
        paths = [p for p in listed.stdout.split("\0") if p and (root / p).is_file()]  # a deleted file is no input
    else:
        entries = [root / name for name in SHIPPED]
        files = [e for e in entries if e.is_file()] + [f for e in entries if e.is_dir() for f in sorted(e.rglob("*"))]
        paths = [str(f.relative_to(root)) for f in files if f.is_file() and "__pycache__" not in f.parts]
    return [p for p in paths if not p.startswith(NOT_INPUTS)]


def in_git_checkout(root: Path) -> bool:
    """Whether root is the top of a git work tree (not a folder inside some other repository)."""
    if shutil.which("git") is None:
        return False
    done = subprocess.run(["git", "-C", str(root), "rev-parse", "--show-toplevel"], capture_output=True, text=True)
    return done.returncode == 0 and Path(done.stdout.strip()).resolve() == root.resolve()


def scratch(tmp_path: Path, root: Path = ROOT) -> Path:
    """tmp_path filled with a copy of root's tracked files, for the documents' outputs: copies, not
    links, so a command that writes a shipped file (`tools/scene_keys.py`) leaves the repository alone."""
    for name in tracked_files(root):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(root / name, tmp_path / name)
    return tmp_path


@pytest.mark.slow
@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_example_runs_as_written(document, tmp_path, monkeypatch):
    runnable = [b for b in blocks(document) if b[0] in SHELL + PYTHON]
    for language, code, reason in runnable:
        for name in named_files(code):
            assert (ROOT / name).is_file(), f"{document.name}: a block names {name}, which the repository does not ship"
    folder = scratch(tmp_path)
    monkeypatch.chdir(folder)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    for language, code, reason in runnable:
        if reason is not None:
            continue
        if language in PYTHON:
            exec(compile(code, f"{document.name} block", "exec"), {"__name__": "__docs__"})
            continue
        for command in shell_commands(code):
            done = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", command], cwd=folder, env=env,
                                  capture_output=True, text=True)
            assert done.returncode == 0, f"{document.name}: `{command}` failed:\n{done.stderr[-3000:]}"


def test_links_point_into_the_repository():
    for document in DOCUMENTS:
        for target in re.findall(r"\]\(([^)\s#]+)", document.read_text()):
            if not re.match(r"[a-z]+://", target):
                assert (document.parent / target).exists(), f"{document.name} links to {target}, not in the repository"


def test_exemptions_are_few_and_say_why():
    exempt = [(d.name, reason) for d in DOCUMENTS for _, _, reason in blocks(d) if reason is not None]
    assert all(len(reason) > 20 for _, reason in exempt)
    assert {name for name, _ in exempt} <= {"PARITY.md"}  # Mitsuba with libLLVM 19, an hour of rendering


def test_scene_key_reference_is_current():
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "scene_keys.py"), "--check"], cwd=ROOT)
    assert done.returncode == 0, "docs/SCENES.md is stale: run `python tools/scene_keys.py` after changing torchvol/scene/model.py"
