# Motion Splats: `make demo` runs the whole product on the bundled clip, `make test`
# runs the suite. Both create .venv (Python 3.11) on first use.
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.requirements-stamp

.PHONY: venv test demo dist clean

venv: $(STAMP)

$(STAMP): requirements.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	@touch $(STAMP)

# The add-on also runs on the oldest Blender the manifest claims (blender_version_min):
# a second, small venv inside .venv with only the bpy 4.2 wheel; numpy, torch and pytest
# come from .venv through a .pth file (appended after its own site-packages, so its bpy wins).
# pytest runs under os._exit: the bpy 4.2 module can crash while Python shuts down, after
# the tests passed.
BPY42 := $(VENV)/bpy42
BPY42_STAMP := $(BPY42)/.bpy-stamp

$(BPY42_STAMP): $(STAMP)
	@test -x $(BPY42)/bin/python || $(PYTHON) -m venv $(BPY42)
	$(BPY42)/bin/python -m pip install --quiet --no-deps bpy==4.2.0
	$(PY) -c "import sysconfig; print(sysconfig.get_paths()['purelib'])" > \
	  "$$($(BPY42)/bin/python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")/motion_splats_engine.pth"
	@touch $(BPY42_STAMP)

# Two workers, one test file each at a time (module fixtures are built once): most of the
# suite waits on subprocesses, imports and single-threaded steps, so on the 2-core CI machine
# this about halves the wall time (docs/benchmarks.md, *Test suite*).
test: $(STAMP) $(BPY42_STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile tests
	$(BPY42)/bin/python -c "import os, sys, pytest; rc = pytest.main(['-q', '-p', 'no:cacheprovider', \
	  '-m', 'not slow', 'tests/addon']); sys.stdout.flush(); sys.stderr.flush(); os._exit(int(rc))"

demo: $(STAMP)
	$(PY) tools/demo.py

# Zipping and validating need only a stdlib Python 3.11; the validator (Blender's
# blender_ext.py) comes from .venv's bpy wheel when present, else `blender` on PATH.
dist:
	$(PYTHON) tools/build_dist.py

clean:
	rm -rf dist out .pytest_cache
