"""`make demo` on a truncated default clip: guards the whole demo path in CI."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # long end-to-end: `pytest -m "not slow"` skips it

REPO = Path(__file__).resolve().parents[1]


def test_demo_pipeline_truncated(tmp_path):
    pytest.importorskip("bpy")
    out = tmp_path / "demo"
    res = subprocess.run([sys.executable, str(REPO / "tools" / "demo.py"), "--out", str(out), "--max-frames", "6",
                          "--steps", "20", "--render-frames", "1,6", "--cycles-samples", "2"],
                         cwd=REPO, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    summary = json.loads(res.stdout[res.stdout.rindex("\n{") + 1:res.stdout.rindex("}") + 1])
    assert Path(summary["blend"]).is_file() and Path(summary["report"]).is_file()
    assert summary["held_out"]["frames"] > 0
    assert len(list((out / "cycles").glob("*.png"))) == 2 and len(list((out / "engine").glob("*.png"))) == 2
    html = Path(summary["report"]).read_text()
    assert "Cycles" in html and "cycles/frame_00001.png" in html
    # the saved .blend reopens with the reconstruction in it
    check = subprocess.run([sys.executable, "-c", (
        "import bpy, sys; bpy.ops.wm.open_mainfile(filepath=sys.argv[1]);"
        "print(sum(1 for o in bpy.data.objects if o.type == 'EMPTY'), sum(1 for o in bpy.data.objects if o.type == 'ARMATURE'))"),
        summary["blend"]], capture_output=True, text=True, timeout=300)
    empties, armatures = map(int, check.stdout.strip().splitlines()[-1].split())
    assert empties > 0 and armatures == 1
