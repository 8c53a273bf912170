"""Running the command line from the tests (not a test module)."""

from __future__ import annotations

import subprocess
import sys


def lightplane(*args, cwd=None, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m lightplane ARGS`` in a fresh process (arguments may be paths), output captured."""
    return subprocess.run([sys.executable, "-m", "lightplane", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


#: the line a process prints before it compiles kernels that are not in the cache (lightplane.core.jit.compile_notice):
#: information, whatever the outcome, so not counted as a message of the command's own
COMPILE_NOTICE = "compiling lightplane's kernels for this machine"


def one_error_line(r, *needles: str) -> str:
    """Assert the command failed as bad input must: exit 2 and one line ``lightplane: error: ...``
    on stderr (besides the compile notice, when the process had kernels to compile), containing each of
    ``needles``; return that line."""
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith(COMPILE_NOTICE)]
    assert len(lines) == 1 and lines[0].startswith("lightplane: error:"), r.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]
