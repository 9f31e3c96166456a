# seqat: `make demo` (simulate a small strip and adjust it), `make test`, `make bench`.
# The virtual environment lives in .venv; the install is redone only when pyproject.toml changes.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.seqat-installed
DEMO := out/demo

.PHONY: demo test bench sysdeps clean

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
	$(BIN)/seqat simulate configs/demo_sim.yaml --out $(DEMO)/flight --seed 1
	$(BIN)/seqat run $(DEMO)/flight --out $(DEMO)/run --method seq-r
	@echo
	@echo "Simulated flight: $(DEMO)/flight (flight.yaml, nav.csv, observations.csv, truth/)"
	@echo "Seq-R results:    $(DEMO)/run (eop.csv, points.csv, run.json)"

test: $(STAMP) sysdeps
	$(BIN)/python -m pytest -q

bench: $(STAMP) sysdeps
	$(BIN)/seqat bench configs/paper_sim.yaml --out out/bench --seed 1 --seed 2 --seed 3 \
		--threshold 0.1 --threshold 0.03 --threshold 0.01

clean:
	rm -rf out .pytest_cache
