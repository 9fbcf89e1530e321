"""Every engine command the README names exists and answers --help."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _readme_commands():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```(?:sh|bash|console)?\n(.*?)```", text, flags=re.S)
    found = set()
    for block in blocks:
        for line in block.splitlines():
            m = re.search(r"python -m (engine(?:\.bench)?)\s+([a-z_]+)", line)
            if m:
                found.add((m.group(1), m.group(2)))
    return sorted(found)


def test_readme_names_engine_commands():
    cmds = _readme_commands()
    assert ("engine", "train") in cmds and ("engine", "render") in cmds
    assert any(mod == "engine.bench" for mod, _ in cmds)


@pytest.mark.parametrize("module,command", _readme_commands())
def test_readme_command_has_help(module, command):
    res = subprocess.run([sys.executable, "-m", module, command, "--help"], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, f"`python -m {module} {command} --help` failed:\n{res.stderr[-2000:]}"
    assert "usage" in res.stdout.lower()


def test_readme_make_targets_exist():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    makefile = (REPO / "Makefile").read_text(encoding="utf-8")
    for target in set(re.findall(r"^make (\w+)", text, flags=re.M)):
        assert re.search(rf"^{target}:", makefile, flags=re.M), f"README names `make {target}`"
