"""The viewer's web server (aiohttp): the page, a small JSON API, and a start-up that listens on loopback only.

GET  /                  the page (static/index.html; static/viewer.js, static/viewer.css under /static)
GET  /api/info          model, controls (axes and trained ranges) and the gallery (PNG data URLs)
GET  /api/view?source=<key>&<axis>=<value>...[&route=1]  one view: {rgb, depth (PNG data URLs),
                        depth_range, model_ms, route, route_features, ...}; route=1: through the fitted route rule
POST /api/upload        multipart form field 'image' -> a new source {key, label, image, initial}
GET  /api/ply?source=<key>&<axis>=<value>...    the view's predicted depth as a coloured point cloud (PLY download)
GET  /api/video?source=<key>&path=orbit|forward&frames=N&fps=F   {gif, mp4 (data URLs), frames, ms}
                                                                 (nvs/viewer/video.py)
Errors are JSON {"error": message} with status 400 (bad input), 413 (file too large) or 500; the server keeps running.
Model work runs on one worker thread, so the event loop stays free and views are computed one at a time.
"""

from __future__ import annotations

import asyncio
import base64
import logging
import math
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError

from nvs.core.errors import UserError
from nvs.viewer.address import bind_error, check_address  # noqa: F401 - check_address: the server's own name too
from nvs.report.pointcloud import ply_bytes
from nvs.viewer.cloud import file_stem, view_points
from nvs.viewer.controls import describe
from nvs.viewer.images import png_data_url, to_uint8
from nvs.viewer.paths import camera_path
from nvs.viewer.session import Source, ViewSession
from nvs.viewer.video import compose_frames, render_views, video_bytes

STATIC = Path(__file__).with_name("static")
MAX_UPLOAD_MB = 20
MAX_VIDEO_FRAMES = 240  # a button press renders at most this many views
log = logging.getLogger(__name__)

SESSION = web.AppKey("session", ViewSession)
INFO = web.AppKey("info", dict)
EXECUTOR = web.AppKey("executor", ThreadPoolExecutor)


def source_json(session: ViewSession, source: Source) -> dict:
    return {"key": source.key, "label": source.label, "image": png_data_url(to_uint8(source.image)),
            "initial": session.controls.initial(source.meta)}


def view_json(session: ViewSession, key: str, values: dict[str, float], route: bool = False) -> dict:
    """Render and encode the PNGs (on the worker thread: both are CPU work)."""
    t0 = time.perf_counter()
    v = session.view(key, values, route)
    features = {k: (f if math.isfinite(f) else None) for k, f in v.route_features.items()} if v.route_features \
        else None  # JSON has no NaN / inf: a feature not computed for this view is null
    return {"rgb": png_data_url(v.rgb), "depth": png_data_url(v.depth) if v.depth is not None else None,
            "depth_range": v.depth_range, "model_ms": v.model_ms, "model_cpu_ms": v.model_cpu_ms,
            "encoded": v.encoded, "route": v.route, "route_features": features,
            "server_ms": 1000 * (time.perf_counter() - t0)}


async def _in_worker(request: web.Request, fn, *args):
    return await asyncio.get_running_loop().run_in_executor(request.app[EXECUTOR], fn, *args)


async def index(request: web.Request) -> web.FileResponse:
    return web.FileResponse(STATIC / "index.html")


async def info(request: web.Request) -> web.Response:
    return web.json_response(request.app[INFO])


def _source_key(request: web.Request) -> str:
    key = request.query.get("source")
    if not key:
        raise UserError("no source given")
    return key


def _pose_values(session: ViewSession, query) -> dict[str, float]:
    values = {}
    for ax in session.controls.axes:
        try:
            values[ax.name] = float(query[ax.name])
        except KeyError:
            raise UserError(f"missing pose value '{ax.name}'") from None
        except ValueError:
            raise UserError(f"{ax.name}={query[ax.name]!r} is not a number") from None
    return values


def _int_param(query, name: str, default: int, lo: int, hi: int) -> int:
    try:
        value = int(query.get(name, default))
    except ValueError:
        raise UserError(f"{name}={query[name]!r} is not a whole number") from None
    if not lo <= value <= hi:
        raise UserError(f"{name}={value}: expected {lo}..{hi}")
    return value


def _route_flag(query) -> bool:
    value = query.get("route", "0")
    if value not in ("0", "1"):
        raise UserError(f"route={value!r}: expected 0 or 1")
    return value == "1"


async def view(request: web.Request) -> web.Response:
    session = request.app[SESSION]
    key = _source_key(request)
    values = _pose_values(session, request.query)
    route = _route_flag(request.query)
    return web.json_response(await _in_worker(request, view_json, session, key, values, route))


def ply_download(session: ViewSession, key: str, values: dict[str, float]) -> tuple[bytes, str]:
    """The view's point cloud as PLY bytes and a file name (on the worker thread)."""
    xyz, rgb, comments = view_points(session, key, values)
    return ply_bytes(xyz, rgb, comments), file_stem(session.source(key).label, values) + ".ply"


async def ply(request: web.Request) -> web.Response:
    session = request.app[SESSION]
    key = _source_key(request)
    values = _pose_values(session, request.query)
    body, name = await _in_worker(request, ply_download, session, key, values)
    return web.Response(body=body, content_type="application/octet-stream",
                        headers={"Content-Disposition": f'attachment; filename="{name}"'})


def video_json(session: ViewSession, key: str, path: str, frames: int, fps: int) -> dict:
    """Render the path and encode both formats (on the worker thread)."""
    t0 = time.perf_counter()
    source = session.source(key)
    poses = camera_path(path, session.controls, source.meta, frames)
    clips = video_bytes(compose_frames(render_views(session, key, poses, progress=False)), fps)
    return {"gif": "data:image/gif;base64," + base64.b64encode(clips["gif"]).decode("ascii"),
            "mp4": "data:video/mp4;base64," + base64.b64encode(clips["mp4"]).decode("ascii"),
            "frames": len(poses), "ms": 1000 * (time.perf_counter() - t0)}


async def video(request: web.Request) -> web.Response:
    session = request.app[SESSION]
    key = _source_key(request)
    path = request.query.get("path", "orbit")
    if path not in ("orbit", "forward"):
        raise UserError(f"path={path!r}: the page renders orbit or forward (custom paths: python -m nvs.render_video)")
    frames = _int_param(request.query, "frames", 48, 2, MAX_VIDEO_FRAMES)
    fps = _int_param(request.query, "fps", 12, 1, 60)
    return web.json_response(await _in_worker(request, video_json, session, key, path, frames, fps))


async def upload(request: web.Request) -> web.Response:
    session = request.app[SESSION]
    try:
        form = await request.post()
    except web.HTTPException:
        raise  # too large: 413 from the middleware
    except (HttpProcessingError, ValueError, AssertionError, LookupError) as err:  # a malformed multipart body
        why = " ".join(str(getattr(err, "message", "") or err).split()) or "cannot parse"
        raise UserError(f"malformed upload: not a multipart form ({err.__class__.__name__}: {why[:200]})") from None
    field = form.get("image")
    if not isinstance(field, web.FileField):
        raise UserError("no file in the upload (form field 'image')")
    data = field.file.read()
    source = await _in_worker(request, session.add_upload, data, field.filename or "upload")
    return web.json_response(source_json(session, source))


@web.middleware
async def json_errors(request: web.Request, handler):
    """Every failure becomes {"error": message}; the page shows it and the server keeps running."""
    try:
        return await handler(request)
    except UserError as err:
        return web.json_response({"error": str(err)}, status=400)
    except web.HTTPRequestEntityTooLarge:
        return web.json_response({"error": f"the file is larger than {MAX_UPLOAD_MB} MB"}, status=413)
    except web.HTTPException:
        raise
    except Exception as err:  # noqa: BLE001 - a bug in one request must not stop the viewer
        log.exception("request %s failed", request.rel_url)
        return web.json_response({"error": f"internal error: {err.__class__.__name__}: {err}"}, status=500)


def build_app(session: ViewSession, meta: dict, threads: int | None = None) -> web.Application:
    """The aiohttp application; ``meta`` (model, data, checkpoint, precision) is shown on the page."""
    app = web.Application(client_max_size=MAX_UPLOAD_MB * 2**20, middlewares=[json_errors])
    app[SESSION] = session
    app[INFO] = {**meta, "image_size": session.image_size, "controls": describe(session.controls),
                 "paths": ["orbit", "forward"] if session.controls.kind == "scene" else ["orbit"],
                 "gallery": [source_json(session, s) for s in session.gallery.values()]}
    app[EXECUTOR] = ThreadPoolExecutor(1, thread_name_prefix="nvs-viewer",
                                       initializer=torch.set_num_threads if threads else None,
                                       initargs=(threads,) if threads else ())

    async def shutdown(app: web.Application) -> None:
        app[EXECUTOR].shutdown(wait=False, cancel_futures=True)

    app.on_cleanup.append(shutdown)
    app.router.add_get("/", index)
    app.router.add_get("/api/info", info)
    app.router.add_get("/api/view", view)
    app.router.add_post("/api/upload", upload)
    app.router.add_get("/api/ply", ply)
    app.router.add_get("/api/video", video)
    app.router.add_static("/static", STATIC)
    return app


async def _serve(app: web.Application, host: str, port: int) -> None:
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    try:
        await web.TCPSite(runner, host, port).start()
    except OSError as err:
        await runner.cleanup()
        raise bind_error(host, port, err) from None
    bound_host, bound_port = runner.addresses[0][:2]
    shown = f"[{bound_host}]" if ":" in bound_host else bound_host
    print(f"viewer: http://{shown}:{bound_port}/  (Ctrl-C stops it)", flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await runner.cleanup()


def serve(app: web.Application, host: str, port: int) -> None:
    """Serve until interrupted; prints the URL (with the chosen port when ``port`` is 0) once listening."""
    try:
        asyncio.run(_serve(app, host, port))
    except KeyboardInterrupt:
        print("viewer: stopped", flush=True)
