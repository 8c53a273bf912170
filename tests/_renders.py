"""Rendered data sets cached between test runs (not a test module)."""

from __future__ import annotations

import hashlib
import tempfile
from pathlib import Path
from typing import Callable


def cached_render(name: str, make: Callable[[], object]) -> Path:
    """Folder of the data set ``make()`` renders (an object with ``save(folder, force=True)``),
    rendered once per renderer version: the folder name carries ``name`` and a hash of the
    renderer's sources.  Written to a temporary folder and renamed, so parallel test workers
    never see a half-written set."""
    import lightplane.simulate.render as R
    import lightplane.simulate.render_core as RC

    key = hashlib.sha1((Path(R.__file__).read_bytes() + Path(RC.__file__).read_bytes())).hexdigest()[:10]
    out = Path(tempfile.gettempdir()) / "lightplane-test-renders" / f"{name}_{key}"
    if not (out / "truth.json").exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=out.parent))
        make().save(tmp, force=True)  # type: ignore[attr-defined]
        try:
            tmp.rename(out)
        except OSError:  # another worker was faster
            pass
    return out


def cached_circle_render(n: int = 5, seed: int = 11, difficulty: str = "realistic", polarity: str = "light") -> Path:
    """Folder with ``n`` rendered circle images, camera.json and truth.json (rendered once per renderer version)."""
    import lightplane.simulate.render as R

    return cached_render(f"circle_{difficulty}_{polarity}_n{n}_s{seed}",
                         lambda: R.render_circle_dataset(n, seed, R.CircleOptions(difficulty=difficulty, polarity=polarity)))
