"""`make dist` builds an installable zip with no tests, docs, tools or caches."""

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_dist_zip_contents(tmp_path):
    out = subprocess.run([sys.executable, str(REPO / "tools" / "build_dist.py"), "--out", str(tmp_path)],
                         capture_output=True, text=True, check=True)
    zpath = Path(out.stdout.strip())
    assert zpath.is_file() and zpath.parent == tmp_path
    with zipfile.ZipFile(zpath) as zf:
        names = zf.namelist()
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    assert manifest["id"] == "motion_splats" and manifest["type"] == "add-on"
    assert "__init__.py" in names and "engine/__main__.py" in names and "addon/fcurves.py" in names
    bad = [n for n in names if n.startswith(("tests/", "docs/", "tools/", ".ci/", ".venv/"))
           or "__pycache__" in n or n.endswith(".pyc") or n in ("Makefile", "requirements.txt", ".gitignore", "pytest.ini")]
    assert not bad, bad
