"""The live sensor's local web page and its JSON / websocket API (Starlette, served by uvicorn).

Every asset of the page ships in the package (``lightplane/live/static``): nothing is loaded from the internet.
The server binds 127.0.0.1 unless told otherwise.  Endpoints (JSON unless said otherwise; a bad request gets a
4xx status and ``{"error": "<one sentence>"}``):

- ``GET /api/status``: source, frame rate, latency (median, p99), dropped frames, points per profile, units,
  recording and scan state, the hardware (lasers, turntable angle);
- ``GET /api/profile``: the latest profile (frame, exposure time, x/z in mm or u/v in px, sigma);
- ``GET /api/preview`` (JSON: the JPEG as base64, ``scale`` (preview px per image px), ``stripe_uv`` and
  ``target``, which the page draws over it, in preview px; a target is an ellipse ``{"center": [u, v],
  "axes": [a, b], "angle_deg": t}``, a list of them, or ``{"points": [[u, v], ...]}``) and
  ``GET /api/preview.jpg`` (the JPEG alone); ``?max_width=N`` px;
- ``GET /api/settings``, ``POST /api/settings`` (``{"name": value, ...}``);
- ``POST /api/laser`` (``{"index": 0, "on": true}``, ``"index": "all"`` for every laser);
- ``POST /api/turntable`` (``{"degrees": 10}``, relative; returns when the table has settled);
- ``POST /api/stage`` (``{"mm": 5}``, relative; returns when the linear stage has settled);
- ``POST /api/record`` (``{"action": "start", "folder": NAME}`` / ``{"action": "stop"}``);
- ``POST /api/scan`` (``{"kind": "turntable"|"linear", "steps": N, "step": deg or mm, "folder": NAME}``),
  ``GET /api/scan``, ``GET /api/scan/points?since=N`` (the cloud's points from row N on, mm);
- ``GET /api/guide``, ``POST /api/guide`` (``{"target_sigma_mm": F, "diameter_mm": F, "working_volume": TEXT}``),
  ``POST /api/guide/accept``, ``POST /api/guide/simulate`` (``{"error_mm": F, "error_deg": F}``; the simulated
  target only): the guided calibration (:mod:`lightplane.live.guide`);
- websocket ``/api/ws``: the engine's events as JSON messages, profiles at most ``profile_hz`` a second (the
  latest one; each carries its frame number) and the status ``status_hz`` a second; the client may send
  ``{"profile_hz": F, "status_hz": F}`` to change the rates.

Folders named in requests are plain names inside the server's output folder.
"""

from __future__ import annotations

import asyncio
import json
import base64
import contextlib
import math
import queue
import re
import socket
import threading
import time
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.live.guide import LiveGuide

if TYPE_CHECKING:
    from lightplane.live.engine import LiveEngine

#: hosts the page answers to when it listens on the loopback interface (a guard against DNS rebinding)
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")


@dataclass(frozen=True)
class ServerOptions:
    """How the page is served: ``output_dir`` receives recordings and scans (one plain-named folder each);
    ``allowed_hosts`` are the Host headers answered (``None``: any); ``profile_hz`` / ``status_hz`` the
    websocket's default rates; ``preview_width`` the preview's default width, px."""

    output_dir: Path = Path("live-output")
    allowed_hosts: tuple[str, ...] | None = None
    profile_hz: float = 20.0
    status_hz: float = 2.0
    preview_width: int = 640
    sensor_name: str | None = None
    extra_status: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("profile_hz", "status_hz"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v <= 1000):
                raise LightplaneError(f"{name} must be a rate in (0, 1000] per second, got {v!r}")
        if not (isinstance(self.preview_width, int) and 16 <= self.preview_width <= 8192):
            raise LightplaneError(f"preview_width must be 16 to 8192 px, got {self.preview_width!r}")


class ApiError(Exception):
    """A request the API refuses: HTTP status and one sentence."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


# ------------------------------------------------------------------ JSON
def jsonable(obj: Any, digits: int = 4) -> Any:
    """``obj`` as plain JSON values: arrays and lists of numbers as (nested) lists rounded to ``digits``
    decimals, NaN and infinities as ``null``, paths as strings, dataclasses as dicts."""
    if isinstance(obj, np.ndarray):
        return _array_json(obj, digits)
    if isinstance(obj, dict):
        return {str(k): jsonable(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        if obj and _is_number(obj[0]) or (obj and isinstance(obj[0], (list, tuple)) and obj[0]
                                           and _is_number(obj[0][0])):
            try:  # a list of numbers (or of rows of numbers): at numpy's speed
                arr = np.asarray(obj)
            except ValueError:  # ragged
                arr = None
            if arr is not None and arr.dtype.kind in "fiu":
                return _array_json(arr, digits)
        return [jsonable(v, digits) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        return round(obj, 9) if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(asdict(obj), digits)
    return obj


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.number)) and not isinstance(v, bool)


def _array_json(obj: np.ndarray, digits: int) -> Any:
    if obj.dtype.kind == "f":
        a = np.round(obj.astype(np.float64), digits)
        if not np.isfinite(a).all():
            b = a.astype(object)
            b[~np.isfinite(a)] = None
            return b.tolist()
        return a.tolist()
    return obj.tolist()


# ------------------------------------------------------------------ request checks
def _body_field(body: dict, name: str, kind: type | tuple[type, ...], default: Any = ...) -> Any:
    if name not in body or (body[name] is None and default is not ...):
        if default is ...:
            raise ApiError(400, f"the request needs the field '{name}'")
        return default
    v = body[name]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if isinstance(v, bool) and bool not in kinds:
        raise ApiError(400, f"field '{name}' must be a {_kind_name(kinds)}, got {v!r}")
    if not isinstance(v, kinds):
        raise ApiError(400, f"field '{name}' must be a {_kind_name(kinds)}, got {v!r:.60}")
    if isinstance(v, float) and not math.isfinite(v):
        raise ApiError(400, f"field '{name}' must be finite, got {v!r}")
    return v


def _kind_name(kinds: tuple[type, ...]) -> str:
    names = {bool: "true/false", int: "number", float: "number", str: "string"}
    return " or ".join(dict.fromkeys(names.get(k, k.__name__) for k in kinds))


FOLDER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def output_folder(base: Path, name: str | None, prefix: str) -> Path:
    """The folder for a recording or scan: ``base/name`` (a plain name: letters, digits, '.', '_', '-'), or a
    new time-stamped one when no name is given; refused when it exists and is not empty."""
    if name is None or name == "":
        stamp = time.strftime("%Y%m%d-%H%M%S")
        path = base / f"{prefix}-{stamp}"
        k = 2
        while path.exists():
            path, k = base / f"{prefix}-{stamp}-{k}", k + 1
        return path
    if not isinstance(name, str) or not FOLDER_NAME.fullmatch(name) or name.endswith(".") or ".." in name:
        raise ApiError(400, f"folder must be a plain name (letters, digits, '.', '_', '-'; up to 100), "
                            f"got {name!r:.60}")
    path = base / name
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise ApiError(409, f"folder {path} already exists and is not empty")
    return path


# ------------------------------------------------------------------ the API
class LiveApi:
    """The endpoints' logic over one engine, without the web framework (each method returns JSON values or
    raises :class:`ApiError` / ``LightplaneError``)."""

    def __init__(self, engine: "LiveEngine", options: ServerOptions) -> None:
        self.engine = engine
        self.options = options
        self.guide = LiveGuide(engine)

    # ------------------------------------------------------------ guided calibration (lightplane.live.guide)
    def guide_state(self) -> dict:
        return jsonable(self.guide.state(), 7)

    def guide_start(self, body: dict) -> dict:
        sigma = float(_body_field(body, "target_sigma_mm", (int, float)))
        return jsonable(self.guide.start(
            sigma, diameter_mm=float(_body_field(body, "diameter_mm", (int, float), 50.0)),
            working_volume=_body_field(body, "working_volume", str, "distance:380,520"),
            percentile=float(_body_field(body, "percentile", (int, float), 100.0))), 7)

    def guide_accept(self, body: dict) -> dict:
        return jsonable(self.guide.accept(), 7)

    def guide_simulate(self, body: dict) -> dict:
        return jsonable(self.guide.place_simulated(float(_body_field(body, "error_mm", (int, float), 3.0)),
                                                   float(_body_field(body, "error_deg", (int, float), 3.0))), 7)

    def status(self) -> dict:
        s = dict(self.engine.status())
        s["hardware"] = self.hardware_state()
        s["sensor"] = self.options.sensor_name
        s.update(self.options.extra_status)
        return jsonable(s, 3)

    def hardware_state(self) -> dict | None:
        hw = self.engine.hardware
        if hw is None:
            return None
        stage = bool(getattr(hw, "has_stage", False))
        return {"lasers": list(hw.laser_states()), "n_lasers": hw.n_lasers, "turntable": bool(hw.has_turntable),
                "angle_deg": float(hw.angle_deg) if hw.has_turntable else None, "stage": stage,
                "position_mm": float(getattr(hw, "position_mm")) if stage else None}

    def profile(self) -> dict:
        p = self.engine.latest_profile()
        if p is None:
            raise ApiError(503, "no profile yet (the live loop has not produced one)")
        return jsonable(p, 4)

    def preview(self, max_width: int | None) -> tuple[bytes, dict]:
        width = self.options.preview_width if max_width is None else max_width
        if not 16 <= width <= 8192:
            raise ApiError(400, f"max_width must be 16 to 8192 px, got {width}")
        got = self.engine.latest_preview(width)
        if got is None:
            raise ApiError(503, "no frame yet (the source has not delivered one)")
        jpeg, meta = got
        return jpeg, jsonable(meta, 2)

    def preview_json(self, max_width: int | None) -> dict:
        jpeg, meta = self.preview(max_width)
        return {**meta, "jpeg_base64": base64.b64encode(jpeg).decode("ascii")}

    def settings(self) -> dict:
        return jsonable(self.engine.settings(), 6)

    def update_settings(self, body: dict) -> dict:
        if not body:
            raise ApiError(400, "the request names no setting to change")
        known = self.settings()
        unknown = [k for k in body if k not in known]
        if unknown:
            raise ApiError(400, f"unknown setting {unknown[0]!r} (known: {', '.join(known)})")
        try:
            return jsonable(self.engine.update_settings(**body), 6)
        except LightplaneError:
            raise
        except (TypeError, ValueError) as e:
            raise ApiError(400, f"bad setting value: {e}") from None

    def _hardware(self):
        hw = self.engine.hardware
        if hw is None:
            raise ApiError(409, "this sensor has no lasers or turntable to control (start it with --hardware)")
        if self.engine.scan_status().get("state") == "running":
            raise ApiError(409, "a scan is running: it drives the lasers and the table until it ends")
        return hw

    def laser(self, body: dict) -> dict:
        hw = self._hardware()
        on = _body_field(body, "on", bool)
        index = _body_field(body, "index", (int, str), 0)
        if index == "all":
            indices = list(range(hw.n_lasers))
        elif isinstance(index, int) and 0 <= index < hw.n_lasers:
            indices = [index]
        else:
            raise ApiError(400, f"laser index must be 0 to {hw.n_lasers - 1} or \"all\", got {index!r:.40}")
        for i in indices:
            hw.set_laser(i, on)
        return {"lasers": list(hw.laser_states())}

    def turntable(self, body: dict) -> dict:
        hw = self._hardware()
        if not hw.has_turntable:
            raise ApiError(409, "this hardware has no turntable")
        degrees = float(_body_field(body, "degrees", (int, float)))
        if abs(degrees) > 3600:
            raise ApiError(400, f"degrees must be within +-3600 (one request), got {degrees}")
        hw.move_turntable(degrees)
        return {"angle_deg": float(hw.angle_deg)}

    def stage(self, body: dict) -> dict:
        hw = self._hardware()
        if not getattr(hw, "has_stage", False):
            raise ApiError(409, "this hardware has no linear stage")
        mm = float(_body_field(body, "mm", (int, float)))
        if abs(mm) > 10000:
            raise ApiError(400, f"mm must be within +-10000 (one request), got {mm}")
        hw.move_stage(mm)
        return {"position_mm": float(hw.position_mm)}

    def record(self, body: dict) -> dict:
        action = _body_field(body, "action", str)
        if action == "start":
            folder = output_folder(self.options.output_dir, _body_field(body, "folder", str, None), "record")
            self.engine.start_recording(folder)
            return {"recording": True, "folder": str(folder)}
        if action == "stop":
            files = self.engine.stop_recording()
            return {"recording": False, "files": jsonable(files)}
        raise ApiError(400, f"action must be \"start\" or \"stop\", got {action!r:.40}")

    def start_scan(self, body: dict) -> dict:
        kind = _body_field(body, "kind", str)
        if kind not in ("turntable", "linear"):
            raise ApiError(400, f"kind must be \"turntable\" or \"linear\", got {kind!r:.40}")
        steps = _body_field(body, "steps", int)
        if not 1 <= steps <= 100000:
            raise ApiError(400, f"steps must be 1 to 100000, got {steps}")
        step = float(_body_field(body, "step", (int, float)))
        if step == 0:
            raise ApiError(400, "step must not be 0 (degrees for a turntable, mm for a linear stage)")
        folder = output_folder(self.options.output_dir, _body_field(body, "folder", str, None), "scan")
        self.engine.start_scan(kind, steps, step, folder)
        return self.scan_status()

    def scan_status(self) -> dict:
        return jsonable(self.engine.scan_status(), 4)

    def scan_points(self, since: int) -> dict:
        if since < 0:
            raise ApiError(400, f"since must be >= 0, got {since}")
        pts = np.asarray(self.engine.scan_points(since), dtype=np.float64).reshape(-1, 3)
        return {"since": since, "count": int(len(pts)), "next": since + int(len(pts)), "units": "mm",
                "points": jsonable(pts.ravel(), 3)}


def _int_query(request, name: str, default: int | None) -> int | None:
    text = request.query_params.get(name)
    if text is None:
        return default
    try:
        return int(text)
    except ValueError:
        raise ApiError(400, f"query parameter '{name}' must be an integer, got {text!r:.40}") from None


async def _json_body(request) -> dict:
    raw = await request.body()
    if not raw.strip():
        return {}
    try:
        body = json.loads(raw)
    except ValueError:
        raise ApiError(400, "the request body is not valid JSON") from None
    if not isinstance(body, dict):
        raise ApiError(400, "the request body must be a JSON object")
    return body


# ------------------------------------------------------------------ the websocket
def _is_profile(event: dict) -> bool:
    return event.get("type") == "profile" or ("type" not in event and "frame" in event
                                              and ("x" in event or "u" in event))


def _drain(q: "queue.Queue[dict]", limit: int = 1000) -> list[dict]:
    out = []
    for _ in range(limit):
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            break
    return out


async def _ws_rates(websocket, rates: dict) -> None:
    """Read the client's messages until it goes: ``{"profile_hz": F, "status_hz": F}`` change the rates."""
    from starlette.websockets import WebSocketDisconnect

    try:
        while True:
            text = await websocket.receive_text()
            with contextlib.suppress(ValueError, TypeError, AttributeError):
                msg = json.loads(text)
                for key in ("profile_hz", "status_hz"):
                    v = msg.get(key)
                    if isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= 1000:
                        rates[key] = float(v)
    except (WebSocketDisconnect, RuntimeError):
        return


async def _ws_stream(websocket, api: LiveApi) -> None:
    """Forward the engine's events to one websocket client until it goes (profiles thinned to the rate)."""
    rates = {"profile_hz": api.options.profile_hz, "status_hz": api.options.status_hz}
    q = api.engine.subscribe()
    reader = asyncio.create_task(_ws_rates(websocket, rates))
    pending: dict | None = None
    last_profile = last_status = 0.0
    try:
        while not reader.done():
            for ev in _drain(q):
                if _is_profile(ev):
                    pending = ev
                else:
                    await websocket.send_json(jsonable(ev, 4))
            now = time.monotonic()
            if pending is not None and now - last_profile >= 1.0 / rates["profile_hz"]:
                await websocket.send_json({"type": "profile", **jsonable(pending, 4)})
                pending, last_profile = None, now
            if now - last_status >= 1.0 / rates["status_hz"]:
                await websocket.send_json({"type": "status", **api.status()})
                last_status = now
            # wake when the next message is due, not more often: the loop beside this one needs the CPU
            now = time.monotonic()
            due_profile = last_profile + 1.0 / rates["profile_hz"]
            if pending is None:  # nothing to send yet: look again in 20 ms at the soonest
                due_profile = max(due_profile, now + 0.02)
            due = min(due_profile, last_status + 1.0 / rates["status_hz"])
            await asyncio.sleep(min(max(due - now, 0.002), 0.1))
    except Exception:  # the client went away mid-send: nothing to report to anyone
        pass
    finally:
        api.engine.unsubscribe(q)
        reader.cancel()
        with contextlib.suppress(BaseException):
            await reader


# ------------------------------------------------------------------ the application
def create_app(engine: "LiveEngine", options: ServerOptions | None = None, *, manage_engine: bool = True):
    """The Starlette application serving the page and the API over ``engine``; with ``manage_engine`` the
    application starts the engine when it starts and stops it when it stops."""
    from starlette.applications import Starlette
    from starlette.middleware import Middleware
    from starlette.middleware.trustedhost import TrustedHostMiddleware
    from starlette.routing import Mount, Route, WebSocketRoute
    from starlette.staticfiles import StaticFiles

    options = options or ServerOptions()
    api = LiveApi(engine, options)

    @contextlib.asynccontextmanager
    async def lifespan(app):
        if manage_engine:
            engine.start()
        try:
            yield
        finally:
            if manage_engine:
                engine.stop()

    routes = [Mount("/api", routes=_api_routes(api, Route, WebSocketRoute)),
              Mount("/", app=StaticFiles(packages=[("lightplane.live", "static")], html=True), name="page")]
    middleware = []
    if options.allowed_hosts is not None:
        middleware.append(Middleware(TrustedHostMiddleware, allowed_hosts=list(options.allowed_hosts)))
    app = Starlette(routes=routes, middleware=middleware, lifespan=lifespan,
                    exception_handlers=_exception_handlers())
    app.state.api = api
    return app


def _exception_handlers() -> dict:
    from starlette.exceptions import HTTPException
    from starlette.responses import JSONResponse

    async def api_error(request, exc: ApiError):
        return JSONResponse({"error": exc.message}, status_code=exc.status)

    async def lightplane_error(request, exc: LightplaneError):
        return JSONResponse({"error": str(exc)}, status_code=400)

    async def http_error(request, exc: HTTPException):
        if exc.status_code == 404:
            message = f"no such page or endpoint: {request.url.path}"
        elif exc.status_code == 405:
            message = f"{request.method} is not allowed on {request.url.path}"
        else:
            message = str(exc.detail)
        return JSONResponse({"error": message}, status_code=exc.status_code, headers=exc.headers)

    return {ApiError: api_error, LightplaneError: lightplane_error, HTTPException: http_error}


def _api_routes(api: LiveApi, Route, WebSocketRoute) -> list:
    from starlette.concurrency import run_in_threadpool
    from starlette.responses import JSONResponse, Response

    def get(fn: Callable[[Any], Any]):
        async def endpoint(request):
            return JSONResponse(await run_in_threadpool(fn, request), headers={"Cache-Control": "no-store"})
        return endpoint

    def post(fn: Callable[[dict], Any]):
        async def endpoint(request):
            body = await _json_body(request)
            return JSONResponse(await run_in_threadpool(fn, body), headers={"Cache-Control": "no-store"})
        return endpoint

    async def preview_jpg(request):
        jpeg, meta = await run_in_threadpool(api.preview, _int_query(request, "max_width", None))
        return Response(jpeg, media_type="image/jpeg",
                        headers={"Cache-Control": "no-store", "X-Preview-Scale": str(meta.get("scale", ""))})

    async def ws(websocket):
        await websocket.accept()
        await _ws_stream(websocket, api)

    return [
        Route("/status", get(lambda r: api.status())),
        Route("/profile", get(lambda r: api.profile())),
        Route("/preview", get(lambda r: api.preview_json(_int_query(r, "max_width", None)))),
        Route("/preview.jpg", preview_jpg),
        Route("/settings", get(lambda r: api.settings())),
        Route("/settings", post(api.update_settings), methods=["POST"]),
        Route("/laser", post(api.laser), methods=["POST"]),
        Route("/turntable", post(api.turntable), methods=["POST"]),
        Route("/stage", post(api.stage), methods=["POST"]),
        Route("/record", post(api.record), methods=["POST"]),
        Route("/scan", get(lambda r: api.scan_status())),
        Route("/scan", post(api.start_scan), methods=["POST"]),
        Route("/scan/points", get(lambda r: api.scan_points(_int_query(r, "since", 0) or 0))),
        Route("/guide", get(lambda r: api.guide_state())),
        Route("/guide", post(api.guide_start), methods=["POST"]),
        Route("/guide/accept", post(api.guide_accept), methods=["POST"]),
        Route("/guide/simulate", post(api.guide_simulate), methods=["POST"]),
        WebSocketRoute("/ws", ws),
    ]


# ------------------------------------------------------------------ serving
def listen(host: str, port: int) -> socket.socket:
    """A socket bound to ``host:port`` (port 0: a free one), or ``LightplaneError`` saying why not."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise LightplaneError(f"cannot listen on {host}:{port}: {e.strerror}") from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(64)
    except OSError as e:
        sock.close()
        raise LightplaneError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    sock.set_inheritable(True)
    return sock


def url_of(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/"


def _uvicorn_server(engine: "LiveEngine", options: ServerOptions | None):
    import uvicorn

    app = create_app(engine, options, manage_engine=False)
    config = uvicorn.Config(app, log_level="warning", access_log=False, timeout_graceful_shutdown=2,
                            ws="auto", lifespan="on")
    return uvicorn.Server(config)


def serve_in_thread(engine: "LiveEngine", sock: socket.socket,
                    options: ServerOptions | None = None) -> Callable[[], None]:
    """Serve on the bound ``sock`` from a background thread of this process (as ``lightplane live`` does,
    beside the engine's threads); returns the function that stops it.  The caller starts and stops the
    engine."""
    server = _uvicorn_server(engine, options)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="lightplane-page", daemon=True)
    thread.start()
    while not server.started and thread.is_alive():
        time.sleep(0.01)

    def stop() -> None:
        server.should_exit = True
        thread.join(10.0)

    return stop


def serve(engine: "LiveEngine", sock: socket.socket, options: ServerOptions | None = None) -> None:
    """Serve the page and the API on the bound ``sock`` until interrupted (Ctrl+C, SIGTERM); the caller starts
    and stops the engine."""
    _uvicorn_server(engine, options).run(sockets=[sock])
