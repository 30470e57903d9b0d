# The one entry point. `make test` is what CI runs (.ci/run).
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(VENV)/bin/pip
export CARGO_TERM_COLOR := never

.PHONY: test venv build cargo-test pytest stubtest bench lint clean

test: build cargo-test pytest stubtest

$(VENV)/.deps: pyproject.toml
	python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q "maturin>=1.9.4,<2" "numpy>=1.24" "click>=8.1" "tqdm>=4.60" \
	  "pytest>=8" "hypothesis>=6.90" "scipy>=1.11" "pytest-benchmark>=4" "mypy>=1.10" "matplotlib>=3.7" "h5py>=3.8" ruff \
	  "pandas>=1.5" "pyarrow>=12" "dask[distributed]>=2023.1"
	touch $@

venv: $(VENV)/.deps

# One release build of the extension; `cargo test --release` then reuses every compiled dependency.
build: venv
	VIRTUAL_ENV=$(abspath $(VENV)) PATH=$(abspath $(VENV))/bin:$$PATH $(VENV)/bin/maturin develop --release -q

cargo-test:
	cargo test --release

pytest: build
	$(PY) -m pytest -q

stubtest: build
	$(PY) -m mypy.stubtest accelcal._core --allowlist stubtest-allowlist.txt

bench: build
	cargo bench --bench core
	$(PY) -m pytest benches -o addopts="" -o python_files="bench_*.py" -p no:cacheprovider -q -s --benchmark-only --benchmark-columns=median,ops

lint:
	cargo fmt --check
	cargo clippy --all-targets --all-features -- -D warnings
	$(VENV)/bin/ruff check python tests benches examples
	$(PY) -m mypy python/accelcal

clean:
	rm -rf $(VENV) target
