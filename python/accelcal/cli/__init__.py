"""The ``accelcal`` command line.

Every command prints a readable table by default and JSON with ``--json``; bad input gives
one line on stderr and exit status 2, never a traceback. One module per command group:
``stream`` (dwells, apply), ``static`` (calibrate static, plan), ``centrifuge``,
``gradiometer``, ``diagnose``, ``demo``, ``fleet`` (fleet runs and the fleet report),
``compare`` (two calibrations of one sensor); shared
options and error handling in ``_common``.
"""

from __future__ import annotations

from . import centrifuge, compare, demo, diagnose, fleet, gradiometer, static, stream  # noqa: F401
from ._common import calibrate, emit_json, friendly, main, write_json_file

__all__ = ["calibrate", "emit_json", "friendly", "main", "write_json_file"]

if __name__ == "__main__":  # pragma: no cover
    main()
