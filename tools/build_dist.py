"""Build the installable extension zip: ``python tools/build_dist.py [--out DIR]``.

Packs the files git lists (tracked plus untracked-but-not-ignored; outside a git
checkout, every file under the repo)
except what ``blender_manifest.toml``'s ``[build] paths_exclude_pattern`` excludes, so
the zip holds the add-on and the engine but no tests, docs, tools or caches. Checks that
the packed manifest parses with ``tomllib`` and names the required fields, then runs
Blender's own extension validator on the zip (``blender_ext.py validate``, the extensions
platform's checks: field lengths, permissions, tags) and fails on any error.

Needs only a Python 3.11+ standard library. The validator is found, in order, at
``$BLENDER_EXT_VALIDATOR`` (a path to ``blender_ext.py``), inside an installed ``bpy``
wheel (this interpreter's or the repo's ``.venv``), or as ``blender --command extension
validate`` with ``blender`` on PATH.
"""

from __future__ import annotations

import argparse
import fnmatch
import importlib.util
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VALIDATOR_ENV = "BLENDER_EXT_VALIDATOR"
#: Where Blender's extension CLI sits inside a ``bpy`` wheel (``bpy/<version>/scripts/...``).
WHEEL_VALIDATOR = "*/scripts/addons_core/bl_pkg/cli/blender_ext.py"
REQUIRED = ("schema_version", "id", "version", "name", "type", "maintainer", "blender_version_min", "license")


def _excluded(rel: str, patterns: list[str]) -> bool:
    """gitignore-style matching of the manifest's patterns against ``rel`` (posix)."""
    parts = rel.split("/")
    for pat in patterns:
        anchored = pat.startswith("/")
        p = pat.strip("/")
        is_dir = pat.endswith("/")
        if anchored:
            target = "/".join(parts[: len(p.split("/"))]) if is_dir else rel
            if fnmatch.fnmatch(target, p) or (is_dir and rel.startswith(p + "/")):
                return True
        else:
            names = parts[:-1] if is_dir else parts
            if any(fnmatch.fnmatch(name, p) for name in names):
                return True
    return False


def list_files(repo: Path) -> list[str]:
    try:
        # tracked files plus new, not ignored ones (work not committed yet still ships)
        out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                             cwd=repo, capture_output=True, check=True)
        files = [f for f in out.stdout.decode().split("\0") if f]
    except (OSError, subprocess.CalledProcessError):
        files = [p.relative_to(repo).as_posix() for p in repo.rglob("*") if p.is_file()]
    return sorted(set(f for f in files if (repo / f).is_file()))


def build(out_dir: Path, repo: Path = REPO) -> Path:
    manifest = tomllib.loads((repo / "blender_manifest.toml").read_text(encoding="utf-8"))
    missing = [k for k in REQUIRED if k not in manifest]
    if missing:
        raise SystemExit(f"blender_manifest.toml lacks {missing}")
    patterns = manifest.get("build", {}).get("paths_exclude_pattern", [])
    files = [f for f in list_files(repo) if not _excluded(f, patterns)]
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    tmp = target.with_suffix(".zip.tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for f in files:
            zf.write(repo / f, f)
    with zipfile.ZipFile(tmp) as zf:
        packed = tomllib.loads(zf.read("blender_manifest.toml").decode("utf-8"))
        if packed["id"] != manifest["id"] or "__init__.py" not in zf.namelist():
            raise SystemExit("packed extension is incomplete")
    tmp.replace(target)
    return target


def _wheel_validators(repo: Path) -> list[Path]:
    """``blender_ext.py`` inside bpy wheels: this interpreter's (found without importing
    bpy) and the repo's ``.venv`` (so a plain python3.11 can validate)."""
    roots = []
    spec = importlib.util.find_spec("bpy")
    if spec is not None and spec.submodule_search_locations:
        roots += [Path(p) for p in spec.submodule_search_locations]
    roots += sorted(repo.glob(".venv/lib/python3*/site-packages/bpy"))
    return [v for root in roots for v in sorted(root.glob(WHEEL_VALIDATOR))]


def validator_command(repo: Path = REPO) -> list[str] | None:
    """Argument list that runs Blender's extension validator (the package path is
    appended), or None when none is found."""
    env = os.environ.get(VALIDATOR_ENV)
    if env:
        if not Path(env).is_file():
            raise SystemExit(f"{VALIDATOR_ENV}={env} is not a file: point it at Blender's "
                             "scripts/addons_core/bl_pkg/cli/blender_ext.py")
        return [sys.executable, env, "validate"]
    found = _wheel_validators(repo)
    if found:
        return [sys.executable, str(found[-1]), "validate"]
    blender = shutil.which("blender")
    if blender:
        return [blender, "--factory-startup", "--background", "--command", "extension", "validate"]
    return None


def validate(package: Path, repo: Path = REPO) -> None:
    """Run Blender's validator on ``package`` (zip or folder); SystemExit with its
    messages on any error or when no validator can be found."""
    cmd = validator_command(repo)
    if cmd is None:
        raise SystemExit(f"no Blender extension validator found for {package.name}: run `make venv` (its bpy "
                         f"wheel ships blender_ext.py), put blender on PATH, or set {VALIDATOR_ENV}")
    res = subprocess.run([*cmd, str(package)], capture_output=True, text=True)
    text = (res.stdout + res.stderr).strip()
    if res.returncode != 0 or "ERROR" in text:
        raise SystemExit(f"Blender's extension validator rejects {package.name} "
                         f"(fix blender_manifest.toml):\n{text}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "dist", help="output folder (default: dist/)")
    parser.add_argument("--repo", type=Path, default=REPO, help=argparse.SUPPRESS)  # tests: another tree
    args = parser.parse_args(argv)
    path = build(args.out, args.repo)
    try:
        validate(path)
    except SystemExit:
        path.unlink(missing_ok=True)  # never leave an invalid package where `make dist` puts its output
        raise
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
