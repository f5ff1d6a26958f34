# retarget: the two commands a new user needs are `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
ICT    := build/ict-facekit/rig.yaml

.PHONY: demo real-demo test bench lint clean sample

# Reinstall only when the package metadata changes.
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e '.[dev,report,detect,usd,batch,rigs,fbx]'
	@touch $@

demo: $(STAMP) $(ICT)
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
	$(BIN)/retarget run configs/real.yaml
	@echo "Rig curves: build/real/frames/curves.csv (one column per ICT slider), curves.npz; Live Link Face: livelink.csv; glTF: animation.glb"

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	@for f in bench/*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

lint: $(STAMP)
	$(BIN)/ruff check retarget_cli tests bench

# Regenerate the committed sample (deterministic: same bytes every time).
sample: $(STAMP)
	$(BIN)/retarget synth sample_data --frames 240 --size 320x320 --seed 0

clean:
	rm -rf build .pytest_cache .ruff_cache
