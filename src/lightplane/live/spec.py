"""Reading a device specification such as ``aravis:Basler-123?exposure=2000&roi=0,0,640,480`` or
``ciclop:/dev/ttyUSB0,speed=100``: the target (a device id, a port, a file) and its options, written either after
``?`` and separated by ``&`` (URL style) or after the first ``,`` and separated by ``,`` (as the other live sources
write them; a region of interest is then ``roi=X:Y:W:H``)."""

from __future__ import annotations

from urllib.parse import parse_qsl

from lightplane.core.errors import LightplaneError


def split_spec(text: str, scheme: str) -> tuple[str, list[tuple[str, str]]]:
    """(target, [(key, value), ...]) of ``text``, with or without its leading ``scheme:``."""
    text = text.strip()
    if text == scheme:
        text = ""
    elif text.startswith(scheme + ":"):
        text = text[len(scheme) + 1:]
    elif text[len(scheme):len(scheme) + 1] in ("?", ",") and text.startswith(scheme):
        text = text[len(scheme):]
    if "?" in text:
        target, _, query = text.partition("?")
        return target, parse_qsl(query, keep_blank_values=True)
    target, _, rest = text.partition(",")
    pairs = []
    for part in filter(None, (p.strip() for p in rest.split(","))):
        key, sep, value = part.partition("=")
        if not sep or not key.strip():
            raise LightplaneError(f"{scheme} option {part!r}: write key=value")
        pairs.append((key.strip(), value.strip()))
    return target, pairs


def parse_roi(text: str) -> tuple[int, int, int, int]:
    """``X,Y,W,H`` or ``X:Y:W:H`` in px."""
    parts = tuple(int(v) for v in text.replace(":", ",").split(","))
    if len(parts) != 4:
        raise ValueError("a region of interest is x, y, width, height")
    return parts
