# seqat: `make demo` (`seqat process` on the rendered Autzen flight and the real 18-image Seneca
# flight), `make test`, `make bench`.
# The virtual environment lives in .venv; the install is redone only when pyproject.toml changes.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.seqat-installed
DEMO := out/demo

.PHONY: demo test test-kernels bench bench-faults bench-fuzz sysdeps clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# open3d (DSM stage) needs Debian's libusb-1.0-0; install it when missing and possible.
sysdeps:
	@if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		echo "installing libusb-1.0-0 for open3d"; \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null) \
			|| echo "warning: could not install libusb-1.0-0; open3d will not import"; \
	else \
		echo "note: open3d needs libusb-1.0: run 'sudo apt-get install libusb-1.0-0' (Debian/Ubuntu)"; \
	fi

demo: $(STAMP) sysdeps
	$(BIN)/seqat process sample_data/autzen_rendered --out $(DEMO)/autzen
	$(BIN)/seqat process sample_data/seneca_mini --out $(DEMO)/seneca
	@echo
	@echo "Rendered Autzen flight (12 images, LiDAR, 36 check points): run + live ortho, COLMAP"
	@echo "reference, report:"
	@echo "  map:     $(DEMO)/autzen/mosaic.tif, $(DEMO)/autzen/cameras.gpkg, $(DEMO)/autzen/dsm.tif"
	@echo "  report:  $(DEMO)/autzen/report.html (and report.pdf)"
	@echo "Real Seneca flight (18 images, nav and camera from EXIF/XMP; no LiDAR, no check points):"
	@echo "  results: $(DEMO)/seneca (eop.csv, points.csv, run.json; reference/)"
	@echo "  report:  $(DEMO)/seneca/report.html (and report.pdf)"

# The suite on TEST_WORKERS processes (pytest-xdist; 2 = the 2-core machine it is budgeted
# on, ~10 min), each with a single-threaded BLAS so that they do not compete for the cores.
TEST_WORKERS ?= 2

test: $(STAMP) sysdeps
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist worksteal

# The estimator's tests on another OpenBLAS kernel than the machine's own (Sandy Bridge: AVX,
# no FMA): results must not depend on the CPU (docs/algorithm.md, *BLAS kernels*).
test-kernels: $(STAMP)
	OPENBLAS_CORETYPE=Sandybridge OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q \
		-p no:cacheprovider -n $(TEST_WORKERS) --dist worksteal \
		tests/seqat tests/pipeline/bench/test_bench_faults.py

bench: $(STAMP) sysdeps
	$(BIN)/seqat bench configs/paper_sim.yaml --out out/bench --seed 1 --seed 2 --seed 3 \
		--threshold 0.1 --threshold 0.03 --threshold 0.01

# Seeded blunders, a GNSS jump and a dropout on the paper strip, a 3-strip block and the
# rendered sample (docs/benchmarks.md, *Faults*).
bench-faults: $(STAMP) sysdeps
	$(BIN)/seqat bench faults --out out/bench_faults --seed 1 --seed 2 --seed 3

# Seeded bad inputs: mutated copies of the sample flights run as subprocesses
# (docs/benchmarks.md, *Fuzz bench*; replay one case with --seed S --case K).
bench-fuzz: $(STAMP) sysdeps
	nice -n 10 $(BIN)/seqat bench fuzz --out out/bench_fuzz --seed 1 --seed 2 --seed 3 \
		--cases 40 --jobs 2

clean:
	rm -rf out .pytest_cache
