"""Running the command line from the tests (not a test module)."""

from __future__ import annotations

import subprocess
import sys


def lightplane(*args, cwd=None, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m lightplane ARGS`` in a fresh process (arguments may be paths), output captured."""
    return subprocess.run([sys.executable, "-m", "lightplane", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


def one_error_line(r, *needles: str) -> str:
    """Assert the command failed as bad input must: exit 2 and one line ``lightplane: error: ...``
    on stderr, containing each of ``needles``; return that line."""
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("lightplane: error:"), r.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]
