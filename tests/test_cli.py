"""The command line end to end (in-process through click's runner)."""

from __future__ import annotations

import re

from click.testing import CliRunner

from accelcal.cli import main


def test_demo_quick_finds_all_dwells() -> None:
    r = CliRunner().invoke(main, ["demo", "--quick"])
    assert r.exit_code == 0, r.output
    m = re.search(r"(\d+)/(\d+) detected dwells lie inside a true static interval", r.output)
    assert m and m.group(1) == m.group(2) == "20"


def test_missing_file_is_one_clear_line() -> None:
    r = CliRunner().invoke(main, ["dwells", "/nonexistent/recording.txt", "--fs", "100"])
    assert r.exit_code == 2
    assert "Traceback" not in r.output
    assert "/nonexistent/recording.txt" in r.output
