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
from lightplane.live.source import Hardware, SimulatedHardware
from lightplane.live.sources import open_source
from lightplane.measure.sensor import Sensor

SOURCE_HELP = ("Frame source: sim:turntable, sim:linear or sim:target (the simulated sensor; options after a comma, "
               "e.g. sim:turntable,scale=0.5,fps=60), uvc:N or /dev/videoN (a UVC camera), a video file or a folder "
               "of images (replayed at their frame rate).")
HARDWARE_HELP = ("Lasers and turntable: sim[:N] (simulated, N lasers; with a simulated source, the lasers and table "
                 "it renders). Default: the source's own (the simulated sensor has them), else none.")


def open_hardware(spec: str | None, source: object) -> Hardware | None:
    """The hardware a ``--hardware`` spec names; ``None``: the source's own, if it has any."""
    own = getattr(source, "hardware", None)
    if spec is None:
        return own
    kind, _, count = spec.partition(":")
    if kind != "sim":
        raise LightplaneError(f"--hardware: unknown hardware {spec!r} (known: sim, sim:N)")
    if own is not None:
        return own
    try:
        n = int(count) if count else 1
    except ValueError:
        raise LightplaneError(f"--hardware: 'sim:{count}' needs a number of lasers, e.g. sim:2") from None
    if not 1 <= n <= 4:
        raise LightplaneError(f"--hardware: sim needs 1 to 4 lasers, got {n}")
    return SimulatedHardware(n_lasers=n)


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
    hw = open_hardware(hardware, src)
    sock = listen(host, port)
    try:
        engine = LiveEngine(src, sensor=sens, hardware=hw)
        sensor_name = str(sensor) if sensor is not None else (
            "simulated" if engine.sensor is not None else None)
        options = ServerOptions(output_dir=output_dir, sensor_name=sensor_name,
                                allowed_hosts=(*LOOPBACK_HOSTS, host) if _is_loopback(host) else None)
        engine.start()
    except BaseException:
        sock.close()
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
