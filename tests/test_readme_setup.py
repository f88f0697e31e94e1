"""The README's two set-up commands pass in order in one clone: command 1 writes `data/clouds`
into the clone, and command 2's docs checks must not see it (they run in a copy of the tracked files).

The clone here is a copy of the tracked files in a fresh git repository (the working tree's
versions, so the test checks the code under test, not the last commit), with the installed package,
as after command 1's `pip install -e .`. Its `pip install` steps are not run (this suite runs in the
installed environment)."""

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from test_docs import ROOT, SHELL, blocks, scratch

NESTED = "TORCHVOL_README_SETUP"  # set in the clone's test run: the test never runs itself again


def setup_commands() -> list[str]:
    """The commands of the README's first shell block (install, generate; install, test), their
    `pip install` steps dropped: [command 1, command 2]."""
    code = next(code for language, code, _ in blocks(ROOT / "README.md") if language in SHELL)
    commands = []
    for line in code.splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            parts = [p.strip() for p in line.split("&&")]
            commands.append(" && ".join(p for p in parts if shlex.split(p)[:2] != ["pip", "install"]))
    return commands


def test_readme_opens_with_generate_then_test():
    generate, run_tests = setup_commands()
    assert shlex.split(generate)[:2] == ["torchvol", "generate"] and "--out" in shlex.split(generate)
    assert shlex.split(run_tests)[:3] == ["python", "-m", "pytest"]


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get(NESTED) == "1", reason="already inside the clone's test run")
def test_readme_commands_pass_in_order_in_one_clone(tmp_path):
    generate, _ = setup_commands()
    clone = tmp_path / "clone"
    clone.mkdir()
    scratch(clone)
    subprocess.run(["git", "init", "-q"], cwd=clone, check=True)
    subprocess.run(["git", "add", "-A"], cwd=clone, check=True)
    env = {**os.environ, NESTED: "1", "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}

    done = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", generate], cwd=clone, env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0, f"command 1 `{generate}` failed:\n{done.stderr[-3000:]}"
    out = Path(shlex.split(generate)[shlex.split(generate).index("--out") + 1])
    assert (clone / out / "manifest.jsonl").is_file(), f"command 1 wrote no dataset to {out}"

    # Command 2 runs the whole suite; its docs checks are the part that reads the clone's folders, and
    # the README's own example (command 1 again, small) is the one that met command 1's dataset. The
    # other documents share its scratch copy (DATASETS.md's also writes data/clouds) but take minutes.
    checks = ["tests/test_docs.py::test_every_example_runs_as_written[README.md]",
              "tests/test_docs.py::test_links_point_into_the_repository",
              "tests/test_docs.py::test_exemptions_are_few_and_say_why"]
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *checks], cwd=clone,
                          env=env, capture_output=True, text=True)
    assert done.returncode == 0, f"command 2's docs checks failed after command 1:\n{done.stdout[-3000:]}"
