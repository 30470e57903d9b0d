# The one entry point. `make test` is what CI runs (.ci/run).
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(VENV)/bin/pip
WHEELS := target/wheels
export CARGO_TERM_COLOR := never

# Development and test dependencies (the package's own come from pyproject.toml).
DEV_DEPS := "maturin>=1.9.4,<2" "numpy>=1.24" "click>=8.1" "tqdm>=4.60" "jsonschema>=4.18" \
  "pytest>=8" "hypothesis>=6.90" "scipy>=1.11" "pytest-benchmark>=4" "mypy>=1.10" \
  "matplotlib>=3.7" "h5py>=3.8" "openpyxl>=3.1" "npTDMS>=1.7" "obspy>=1.4" "rosbags>=0.10" \
  "pandas>=2.0" "pyarrow>=14" "dask[distributed]>=2024.1" ruff

.PHONY: test venv build cargo-test pytest stubtest lint wheel wheel-check bench bench-bigfile clean

# One release build of the extension serves pytest, stubtest and the wheel (same features,
# same profile: maturin reuses every compiled artefact); `cargo test --release` reuses the
# compiled dependencies.
test: build lint cargo-test pytest stubtest wheel-check

$(VENV)/.deps: pyproject.toml Makefile
	python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q $(DEV_DEPS)
	touch $@

venv: $(VENV)/.deps

# A stale per-version extension (e.g. _core.cpython-311-*.so from a non-abi3 build) would
# shadow the abi3 one that maturin installs: remove any before installing.
build: venv
	rm -f python/accelcal/_core.*.so
	VIRTUAL_ENV=$(abspath $(VENV)) PATH=$(abspath $(VENV))/bin:$$PATH $(VENV)/bin/maturin develop --release -q

cargo-test:
	cargo test --release

pytest: build
	$(PY) -m pytest -q

stubtest: build
	$(PY) -m mypy.stubtest accelcal._core --allowlist stubtest-allowlist.txt

lint: venv
	cargo fmt --check
	cargo clippy --all-targets --all-features -- -D warnings
	$(VENV)/bin/ruff check python tests benches examples
	$(PY) -m mypy python/accelcal

# An abi3 wheel (CPython >= 3.10) in target/wheels.
wheel: venv
	rm -f $(WHEELS)/accelcal-*.whl
	$(VENV)/bin/maturin build --release -q -o $(WHEELS)

# The wheel installs into a clean virtual environment and runs the main job.
wheel-check: wheel
	rm -rf target/wheel-venv
	python3 -m venv target/wheel-venv
	target/wheel-venv/bin/pip install -q $(WHEELS)/accelcal-*.whl
	cd target && wheel-venv/bin/accelcal demo --quick --no-figures > wheel-demo.txt
	grep -q "Static field calibration" target/wheel-demo.txt
	@echo "wheel-check: $$(ls $(WHEELS)/accelcal-*.whl) installs into a clean venv and runs 'accelcal demo --quick'"

bench: build
	cargo bench --bench core
	$(PY) -m pytest benches -o addopts="" -o python_files="bench_*.py" -p no:cacheprovider -q -s --benchmark-only --benchmark-columns=median,ops

clean:
	rm -rf $(VENV) target

# Big recordings (about 0.75 GB of text at 2e7 rows): reader and streaming commands against
# pandas.read_csv, time and peak memory; ROWS=1e6 for a quick look.
ROWS ?= 2e7
bench-bigfile: build
	$(PY) benches/bench_bigfile.py --rows $(ROWS)
