"""Results as plain Python values for JSON: the package's one converter of numpy arrays and
scalars (models, reports, fits and the command line's ``--json``)."""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any

import numpy as np


def plain(v: Any, *, strict: bool = False) -> Any:
    """``v`` with every numpy array and scalar in it as Python lists and numbers, through
    dicts, lists and tuples (as lists) and dataclasses (as dicts of their fields); anything
    else as it is.

    ``strict``: JSON without NaN, as the command line writes it: NaN and inf as None, and
    dict keys as text. Otherwise NaN and inf stay floats (``json.dumps`` writes ``NaN``,
    ``Infinity``) and keys stay as they are.
    """
    if isinstance(v, np.ndarray):
        return plain(v.tolist(), strict=True) if strict else v.tolist()
    if isinstance(v, dict):
        return {(str(k) if strict else k): plain(x, strict=strict) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x, strict=strict) for x in v]
    if strict and isinstance(v, (float, np.floating)):
        x = float(v)
        return x if math.isfinite(x) else None
    if isinstance(v, np.generic):
        return v.item()
    if hasattr(v, "__dataclass_fields__"):
        return {f.name: plain(getattr(v, f.name), strict=strict) for f in fields(v)}
    return v
