"""Every example in the user guides runs against the current code, and prints what the guide
shows after it (numbers to the digits shown; a ``...`` stands for anything).

Python blocks run in order in one namespace per guide; shell lines that call ``accelcal`` run
through click's runner; ``printf ... > file`` lines are honoured (the gradiometer guide makes
its table that way). The blocks run as the reader's script would (``__name__`` is
``"__main__"``, so code under the guard runs). The working folder is a scratch folder with
the public recordings in ``data/``, as each guide tells its reader to lay them out.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import shlex
import subprocess
from pathlib import Path

import matplotlib
import pytest
from accelcal.cli import main
from click.testing import CliRunner
from conftest import shared_root

ROOT = Path(__file__).resolve().parents[1]
GUIDES = sorted((ROOT / "docs").glob("guide-*.md"))


def _blocks(text: str) -> list[tuple[str, str, str | None]]:
    """The python and sh blocks in order, each with the plain block that follows it directly
    (its output as the guide shows it), or None."""
    fences = list(re.finditer(r"^```(\w*)\n(.*?)^```\n?", text, re.S | re.M))
    out: list[tuple[str, str, str | None]] = []
    for i, m in enumerate(fences):
        if m.group(1) not in ("python", "sh"):
            continue
        nxt = fences[i + 1] if i + 1 < len(fences) else None
        shown = (nxt.group(2) if nxt is not None and nxt.group(1) == ""
                 and not text[m.end():nxt.start()].strip() else None)
        out.append((m.group(1), m.group(2), shown))
    return out


_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def _pattern(shown: str) -> re.Pattern[str]:
    """A regex for printed text that the guide shows as ``shown``: whitespace runs match any
    whitespace, a line ``...`` (or a trailing ``...`` in a line) matches anything, and every
    number is captured to be compared with a tolerance."""
    parts: list[str] = []
    for tok in shown.split():
        if tok == "...":
            parts.append(r"(?:.|\n)*?")
            continue
        pos, piece = 0, ""
        for m in _NUMBER.finditer(tok):
            piece += re.escape(tok[pos:m.start()]) + "(" + _NUMBER.pattern + ")"
            pos = m.end()
        parts.append(piece + re.escape(tok[pos:]))
    return re.compile(r"\s*" + r"\s+".join(parts) + r"\s*")


def _close(shown: str, printed: str) -> bool:
    """Integers agree exactly; other numbers to one unit in the last digit the guide shows, or
    1e-6 relative."""
    a, b = float(shown), float(printed)
    if re.fullmatch(r"[-+]?\d+", shown):
        return a == b
    frac = shown.lower().split("e")[0]
    digits = len(frac.split(".")[1]) if "." in frac else 0
    exp = int(shown.lower().split("e")[1]) if "e" in shown.lower() else 0
    return abs(a - b) <= max(1.01 * 10.0 ** (exp - digits), 1e-6 * abs(a))


def check_output(shown: str, printed: str, where: str) -> None:
    """Assert that ``printed`` is what the guide shows after the block ``where``."""
    m = _pattern(shown).fullmatch(printed)
    assert m is not None, f"{where}: the guide shows\n{shown}\nbut the code prints\n{printed}"
    want = [t for t in _NUMBER.findall(" ".join(x for x in shown.split() if x != "..."))]
    got = list(m.groups())
    bad = [(w, g) for w, g in zip(want, got, strict=True) if not _close(w, g)]
    assert not bad, f"{where}: numbers differ (shown, printed): {bad}\nprinted:\n{printed}"


def _run_shell(line: str, cwd: Path) -> str:
    """Run one shell line of a guide; what it prints to the terminal."""
    cmd = re.sub(r"\s{2,}#.*$", "", line).strip()
    if not cmd or cmd.startswith(("pip ", "make", "#")):
        return ""
    if cmd.startswith("printf"):
        subprocess.run(cmd, shell=True, cwd=cwd, check=True)
        return ""
    out_file = None
    if " > " in cmd:
        cmd, out_file = (c.strip() for c in cmd.split(" > ", 1))
    args = shlex.split(cmd)
    assert args[0] == "accelcal", f"unexpected shell line in a guide: {line}"
    r = CliRunner().invoke(main, args[1:])
    assert r.exit_code == 0, f"{line}\n{r.output}"
    if out_file:
        (cwd / out_file).write_text(r.output)
        return ""
    return r.output


@pytest.mark.parametrize("guide", GUIDES, ids=[g.stem for g in GUIDES])
def test_guide_examples_run(guide: Path, tmp_path: Path) -> None:
    matplotlib.use("Agg")
    work = tmp_path / "main"
    work.mkdir()
    # The guides read the public recordings from a data/ folder beside the user's script.
    (work / "data").symlink_to(shared_root() / "data")
    (work / "examples").symlink_to(ROOT / "examples")
    blocks = _blocks(guide.read_text())
    assert blocks, f"{guide.name} has no examples"
    # "__main__", as in the reader's script: the fleet guide's blocks run under
    # 'if __name__ == "__main__":' (its process pools import the script).
    ns: dict[str, object] = {"__name__": "__main__"}
    old = Path.cwd()
    os.chdir(work)
    try:
        for i, (lang, code, shown) in enumerate(blocks):
            if lang == "python":
                buf = io.StringIO()
                with contextlib.redirect_stdout(buf):
                    exec(compile(code, f"{guide.name}:block{i}", "exec"), ns)
                if shown is not None:
                    check_output(shown, buf.getvalue(), f"{guide.name}:block{i}")
            else:
                # A shell block shows the output of its first command that prints.
                printed = [p for p in (_run_shell(ln, work) for ln in code.splitlines()) if p]
                if shown is not None:
                    check_output(shown, printed[0] if printed else "", f"{guide.name}:block{i}")
    finally:
        os.chdir(old)
        import matplotlib.pyplot as plt

        plt.close("all")


def test_output_check_catches_a_changed_figure() -> None:
    shown = "DwellSet(39 dwells) noise std: [3.11 3.03 3.11]\n  #  start\n... 36 more\n"
    check_output(shown, "DwellSet(39 dwells)  noise std: [3.11 3.03 3.114]\n  #  start\n"
                 "  0  60\n... 36 more\n", "same")
    for printed in ("DwellSet(38 dwells) noise std: [3.11 3.03 3.11]\n  #  start\n... 36 more\n",
                    "DwellSet(39 dwells) noise std: [3.11 3.05 3.11]\n  #  start\n... 36 more\n",
                    "DwellSet(39 dwells) noise std: [3.11 3.03 3.11]\n"):
        with pytest.raises(AssertionError):
            check_output(shown, printed, "changed")
    check_output("p 1.2e-08", "p 1.24e-08", "exponent")
    with pytest.raises(AssertionError):
        check_output("p 1.2e-08", "p 1.2e-07", "exponent")
