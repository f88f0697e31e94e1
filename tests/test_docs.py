"""Documentation that is generated from code stays in step with it."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_scene_key_reference_is_current():
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "scene_keys.py"), "--check"], cwd=ROOT)
    assert done.returncode == 0, "docs/SCENES.md is stale: run `python tools/scene_keys.py` after changing torchvol/scene.py"
