"""The newcomer's pages run as written: every Python block of Home, Getting started and
Rigid bodies and Lie groups,
in order, as one script in a fresh process (as a user would paste them, without the
test suite's JAX settings)."""

import pathlib
import re
import subprocess
import sys

import pytest


DOCS = pathlib.Path(__file__).parent.parent / "docs"
_PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def _run(source: str, tmp_path: pathlib.Path, name: str):
    script = tmp_path / name
    script.write_text(source)
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path
    )
    assert done.returncode == 0, f"{name} failed:\n{done.stderr[-3000:]}"
    return done.stdout


@pytest.mark.parametrize("page", ["index.md", "getting-started.md", "lie-groups.md"])
def test_page_code_blocks_run(page, tmp_path):
    blocks = _PYTHON_BLOCK.findall((DOCS / page).read_text())
    assert blocks, f"{page} has no Python block"
    stdout = _run("\n".join(blocks), tmp_path, "page.py")
    if page == "getting-started.md":
        # The study prints its table and verdict.
        assert "| MidpointVI |" in stdout and "Verdict" in stdout
