"""docs/api.md's example runs as written, and does what it says."""

import re
import subprocess
import sys

from conftest import ROOT


def test_the_api_example_runs(tmp_path, synth_scene):
    synth_scene(tmp_path / "scene", 0)
    code = re.search(r"```python\n(.*?)```", (ROOT / "docs" / "api.md").read_text(), re.S).group(1)
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    verdict, mm, _, deg, _ = proc.stdout.splitlines()[0].split()
    assert verdict == "ok" and float(mm) < 3 and float(deg) < 0.05, proc.stdout
    assert "depth on" in proc.stdout and float(proc.stdout.split("edges against chance:")[1]) > 1.25


def test_import_is_light():
    """`import rgbd_gt` loads no step (nor torch) until a name is used."""
    code = "import sys, rgbd_gt; print('torch' in sys.modules, 'rgbd_gt.steps' in sys.modules, len(rgbd_gt.__all__))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[:2] == ["False", "False"] and int(out[2]) > 10
