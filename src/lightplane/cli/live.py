"""``lightplane live``: drive a sensor live and serve its page on this computer."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Optional

import typer

from lightplane.cli._common import app, handles_errors
from lightplane.core.errors import LightplaneError
from lightplane.live.engine import LiveEngine
from lightplane.live.server import LOOPBACK_HOSTS, ServerOptions, listen, serve, url_of
from lightplane.live.hardware import open_hardware
from lightplane.live.source import Hardware
from lightplane.live.sources import open_source
from lightplane.measure.sensor import Sensor

SOURCE_HELP = ("Frame source: sim:turntable, sim:linear or sim:target (the simulated sensor; options after a comma, "
               "e.g. sim:turntable,scale=0.5,fps=60), uvc:N or /dev/videoN (a UVC camera), a video file or a folder "
               "of images (replayed at their frame rate).")
HARDWARE_HELP = ("Lasers and turntable: ciclop:PORT (Horus firmware), fabscan:PORT (FabScanPi HAT), sim[:N] "
                 "(simulated; with the simulated sensor, the lasers and table it renders), simdevice[:ciclop|:fabscan] "
                 "(a board simulated on a pseudo-terminal); options after '?' (see the live hardware page). "
                 "Default: the source's own (the simulated sensor has them), else none.")


def live_hardware(spec: str | None, source: object) -> Hardware | None:
    """The hardware a ``--hardware`` spec names (:func:`lightplane.live.hardware.open_hardware`); ``None``,
    or ``sim`` with a source that has its own simulated hardware: the source's own."""
    own = getattr(source, "hardware", None)
    if spec is None or (own is not None and spec.strip() in ("sim", "sim:")):
        return own
    try:
        return open_hardware(spec)
    except LightplaneError as e:
        raise LightplaneError(f"--hardware: {e}") from None


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@app.command("live")
@handles_errors
def live_cmd(
    source: str = typer.Option(..., "--source", help=SOURCE_HELP),
    sensor: Optional[Path] = typer.Option(None, "--sensor", help="Sensor file (camera and light planes): profiles "
                                          "in mm. Without one, profiles are in image pixels."),
    port: int = typer.Option(8000, "--port", min=0, max=65535, help="Port of the page (0: any free port)."),
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on (default: this computer only; "
                             "0.0.0.0 opens the page, and the sensor's controls, to the network)."),
    hardware: Optional[str] = typer.Option(None, "--hardware", help=HARDWARE_HELP),
    output_dir: Path = typer.Option(Path("live-output"), "--output-dir", help="Folder for recordings and scans "
                                    "(one folder each inside it)."),
) -> None:
    """Serve a live page for a sensor: the image with the stripe, the profile, rates, settings, record and scan.

    Example: lightplane live --source sim:turntable --port 8000   (then open http://127.0.0.1:8000/)

    The page and its JSON / websocket API (/api/status, /api/profile, /api/record, /api/scan, /api/ws...)
    are served from this computer; nothing is loaded from the internet. Ctrl+C stops.
    """
    sens = Sensor.load(sensor) if sensor is not None else None
    if output_dir.exists() and not output_dir.is_dir():
        raise LightplaneError(f"--output-dir: {output_dir} exists and is not a folder")
    src = open_source(source)
    hw = live_hardware(hardware, src)
    try:
        sock = listen(host, port)
    except BaseException:
        if hw is not None:
            hw.close()
        raise
    try:
        engine = LiveEngine(src, sensor=sens, hardware=hw)
        sensor_name = str(sensor) if sensor is not None else (
            "simulated" if engine.sensor is not None else None)
        options = ServerOptions(output_dir=output_dir, sensor_name=sensor_name,
                                allowed_hosts=(*LOOPBACK_HOSTS, host) if _is_loopback(host) else None)
        engine.start()
    except BaseException:
        sock.close()
        if hw is not None:
            hw.close()
        raise
    try:
        units = "mm" if engine.units == "mm" else "px (no sensor file)"
        print(f"lightplane live: {url_of(sock)}  (source {src.name}, profiles in {units}; Ctrl+C stops)",
              flush=True)
        serve(engine, sock, options)
    finally:
        engine.stop()
        if hw is not None:
            hw.close()
        sock.close()
