"""Every example in the user guides runs against the current code.

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


def _blocks(text: str) -> list[tuple[str, str]]:
    return re.findall(r"```(python|sh)\n(.*?)```", text, re.S)


def _run_shell(line: str, cwd: Path) -> None:
    cmd = re.sub(r"\s{2,}#.*$", "", line).strip()
    if not cmd or cmd.startswith(("pip ", "make", "#")):
        return
    if cmd.startswith("printf"):
        subprocess.run(cmd, shell=True, cwd=cwd, check=True)
        return
    out_file = None
    if " > " in cmd:
        cmd, out_file = (c.strip() for c in cmd.split(" > ", 1))
    args = shlex.split(cmd)
    assert args[0] == "accelcal", f"unexpected shell line in a guide: {line}"
    r = CliRunner().invoke(main, args[1:])
    assert r.exit_code == 0, f"{line}\n{r.output}"
    if out_file:
        (cwd / out_file).write_text(r.output)


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
        for i, (lang, code) in enumerate(blocks):
            if lang == "python":
                with contextlib.redirect_stdout(io.StringIO()):
                    exec(compile(code, f"{guide.name}:block{i}", "exec"), ns)
            else:
                for line in code.splitlines():
                    _run_shell(line, work)
    finally:
        os.chdir(old)
        import matplotlib.pyplot as plt

        plt.close("all")
