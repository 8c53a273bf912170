"""Every shell command shown in README.md and docs/*.md runs.

The documentation writes commands in fenced code blocks, one per line after a ``$ `` prompt
(a line ending in ``\\`` continues on the next one); the other lines of such a block are the
output the command printed. For each markdown file the commands run in order, in a fresh
temporary directory, under ``bash -e`` with this interpreter's ``bin`` folder first on PATH.

Commands that read the real photographs name them through ``$LIGHTPLANE_DATA``, which this
test points at ``../shared/data`` (beside the repository). The blocks holding such commands
run as their own group, in their own directory, and are skipped with the reason when that
folder is absent.

Not run here, on purpose (see ``EXCLUDED``): ``make`` targets, which are the test suite
itself and the demo (its own test, ``test_demo.py``), and the install commands, which would install
lightplane from PyPI into a new virtual environment: the environment running this test is
that install.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]

# command prefix -> why it is not run by this test
EXCLUDED = {
    "make ": "make targets are the test suite itself and the demo (test_demo.py)",
    "python3 -m venv ": "install step: the environment running these tests is that install",
    ".venv/bin/pip install ": "install step: installs from PyPI; the environment running these tests is that install",
    "pip install ": "install step: installs from PyPI; the environment running these tests is that install",
}

FENCE = re.compile(r"^(\s*)(```|~~~)")


def extract_blocks(text: str) -> list[list[str]]:
    """The commands of each fenced block that holds ``$ `` lines, in order (continuations joined)."""
    blocks: list[list[str]] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence = m.group(1), m.group(2)
        i += 1
        body: list[str] = []
        while i < len(lines) and not lines[i].strip().startswith(fence):
            line = lines[i]
            body.append(line[len(indent):] if line.startswith(indent) else line.lstrip())
            i += 1
        i += 1  # the closing fence
        commands: list[str] = []
        j = 0
        while j < len(body):
            if body[j].startswith("$ "):
                cmd = body[j][2:]
                while cmd.endswith("\\") and j + 1 < len(body):
                    j += 1
                    cmd = cmd + "\n" + body[j]
                commands.append(cmd)
            j += 1
        if commands:
            blocks.append(commands)
    return blocks


def excluded_reason(cmd: str) -> str | None:
    for prefix, reason in EXCLUDED.items():
        if cmd.lstrip().startswith(prefix):
            return reason
    return None


def needs_data(block: list[str]) -> bool:
    return any("LIGHTPLANE_DATA" in c for c in block)


def command_groups() -> list:
    """One pytest parameter per (file, group): 'synthetic' or 'realdata' commands, in file order."""
    params = []
    for path in DOC_FILES:
        blocks = extract_blocks(path.read_text(encoding="utf-8"))
        for group in ("synthetic", "realdata"):
            cmds = [c for b in blocks if needs_data(b) == (group == "realdata") for c in b
                    if excluded_reason(c) is None]
            if cmds:
                marks = [pytest.mark.realdata] if group == "realdata" else []
                params.append(pytest.param(path, cmds, id=f"{path.relative_to(ROOT)}-{group}", marks=marks))
    return params


GROUPS = command_groups()


def test_the_docs_show_commands():
    """The extractor finds the README's worked example and leaves out exactly the excluded commands."""
    blocks = extract_blocks((ROOT / "README.md").read_text(encoding="utf-8"))
    cmds = [c for b in blocks for c in b]
    assert "make demo" in cmds and "make test" in cmds
    assert all(excluded_reason(c) for c in ("make demo", "make test"))
    assert sum(c.startswith("lightplane ") for c in cmds) >= 4
    assert GROUPS


@pytest.mark.slow
@pytest.mark.parametrize(("doc", "commands"), GROUPS)
def test_doc_commands_run(doc: Path, commands: list[str], tmp_path: Path):
    if any("LIGHTPLANE_DATA" in c for c in commands) and not DATA.is_dir():
        pytest.skip(f"{DATA} (the real photographs) is absent")
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env["LIGHTPLANE_DATA"] = str(DATA)
    env.setdefault("COLUMNS", "120")
    script = "\n".join(commands) + "\n"
    (tmp_path / "commands.sh").write_text(script, encoding="utf-8")
    run = subprocess.run(["bash", "-e", "-x", "commands.sh"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=900)
    out = (run.stdout + run.stderr)[-4000:]
    assert run.returncode == 0, f"{doc.name}: a command failed (exit {run.returncode}):\n{out}"
