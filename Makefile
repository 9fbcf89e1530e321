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

test: $(STAMP)
	$(PY) -m pytest -q tests

demo: $(STAMP)
	$(PY) tools/demo.py

# Zipping and validating need only a stdlib Python 3.11; the validator (Blender's
# blender_ext.py) comes from .venv's bpy wheel when present, else `blender` on PATH.
dist:
	$(PYTHON) tools/build_dist.py

clean:
	rm -rf dist out .pytest_cache
