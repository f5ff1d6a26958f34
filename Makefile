# retarget: the two commands a new user needs are `make demo` and `make test`.
#
# Python 3.11, 3.12 or 3.13. `make test PYTHON=python3.13` picks one (a command on PATH, a pyenv version's
# command, or a path) and installs into .venv-3.13; without PYTHON: python3 when it is supported, else the
# newest python3.1x on PATH, in .venv (tools/find-python finds it; docs/python.md).
PYINFO := $(shell tools/find-python $(PYTHON) 2>/dev/null)
PYVER  := $(firstword $(PYINFO))
PYEXE  := $(lastword $(PYINFO))
ifdef PYTHON
VENV   ?= .venv-$(PYVER)
else
VENV   ?= .venv
endif
BIN    := $(VENV)/bin
# The stamp names the Python version, so a .venv made by another python3 than today's is made anew.
STAMP  := $(VENV)/.installed-$(PYVER)
ICT    := build/ict-facekit/rig.yaml
# Says which interpreter and which virtual environment a target runs with.
SAY_PYTHON = @$(BIN)/python -c 'import os, sys; print("make: Python", sys.version.split()[0], "(" + \
	os.path.realpath(sys._base_executable) + ") in $(VENV)")'

.PHONY: demo real-demo test bench lint clean sample

# Reinstall only when the package metadata changes (or the venv is missing, or of another Python version).
$(STAMP): pyproject.toml
	@tools/find-python $(PYTHON) >/dev/null  # its one-line error, or its warning (a version not tested on)
	@if [ -x $(BIN)/python ] && [ "$$($(BIN)/python -c 'import sys; print("%d.%d" % sys.version_info[:2])' \
		2>/dev/null)" = "$(PYVER)" ]; then :; else \
		echo "make: creating $(VENV) with Python $(PYVER) ($(PYEXE))"; $(PYEXE) -m venv --clear $(VENV); fi
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e '.[dev,report,detect,usd,batch,rigs,fbx]'
	@touch $@

demo: $(STAMP) $(ICT)
	$(SAY_PYTHON)
	$(BIN)/retarget run configs/sample.yaml
	$(BIN)/retarget -q preview configs/sample.yaml -o build/sample/preview.mp4
	$(BIN)/retarget -q report configs/sample.yaml -o build/sample/report.html
	@echo "Outputs: build/sample/ (landmarks.npz, keys.json, weights.npz, weights.csv, targets/, frames/: frame_*.obj, weights.csv, animation.exr/.json, animation.glb)"
	@echo "Preview: build/sample/preview.mp4"
	@echo "Report:  build/sample/report.html"
	$(BIN)/retarget run configs/real.yaml
	@echo "Real clip onto the ICT FaceKit: build/real/frames/curves.csv (the rig's sliders per frame), curves.npz, livelink.csv, animation.glb"

# Your video, your rig: the real clip sample_data/real/d3.mp4 onto the ICT FaceKit (both MIT), configs/real.yaml.
$(ICT): sample_data/ict/ict-facekit-rig.tar.xz sample_data/ict/rig.yaml
	@mkdir -p build
	tar -xJf sample_data/ict/ict-facekit-rig.tar.xz -C build
	cp sample_data/ict/rig.yaml $@

real-demo: $(STAMP) $(ICT)
	$(SAY_PYTHON)
	$(BIN)/retarget run configs/real.yaml
	@echo "Rig curves: build/real/frames/curves.csv (one column per ICT slider), curves.npz; Live Link Face: livelink.csv; glTF: animation.glb"

# The detector's tests fail instead of skipping when it cannot load its model (the extra 'detect' is installed).
test: $(STAMP)
	$(SAY_PYTHON)
	RETARGET_REQUIRE_DETECTOR=1 $(BIN)/python -m pytest -q

bench: $(STAMP)
	$(SAY_PYTHON)
	@for f in bench/*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

lint: $(STAMP)
	$(BIN)/ruff check retarget_cli tests bench tools

# Regenerate the committed sample (deterministic: same bytes every time).
sample: $(STAMP)
	$(BIN)/retarget synth sample_data --frames 240 --size 320x320 --seed 0

clean:
	rm -rf build .pytest_cache .ruff_cache
