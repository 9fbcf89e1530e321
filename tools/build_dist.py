"""Build the installable extension zip: ``python tools/build_dist.py [--out DIR]``.

Packs the files git lists (tracked plus untracked-but-not-ignored; outside a git
checkout, every file under the repo)
except what ``blender_manifest.toml``'s ``[build] paths_exclude_pattern`` excludes, so
the zip holds the add-on and the engine but no tests, docs, tools or caches. Checks that
the packed manifest parses with ``tomllib`` and names the required fields.
"""

from __future__ import annotations

import argparse
import fnmatch
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "dist", help="output folder (default: dist/)")
    args = parser.parse_args(argv)
    path = build(args.out)
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
