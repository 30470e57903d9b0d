"""Collect the pytest-benchmark files ``benches/bench_<domain>.py`` (pytest's default pattern
only collects ``test_*.py``), so ``make bench`` (``pytest benches --benchmark-only``) runs them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest


def pytest_collect_file(file_path: Path, parent: Any) -> pytest.Module | None:
    if file_path.suffix == ".py" and file_path.name.startswith("bench_"):
        return pytest.Module.from_parent(parent, path=file_path)
    return None
