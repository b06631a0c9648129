"""``polyvec serve [FOLDER] [--port N] [--host H] [key=value ...]``: correct a folder's drawings in the browser.

A local web app (starlette, run by uvicorn) on 127.0.0.1 by default: the folder's drawings with
thumbnails and status, each opening its inspection page (:mod:`pipeline.page`) live. A click on the
drawing adds, removes or retypes a keypoint; the page sends the edits, the server writes
``<stem>.keypoints.json`` beside the drawing (the file the static page's "save edits" downloads, and
the one ``polyvec`` picks up) and re-runs the drawing through the store — keypoint_edits → topology →
flow → select → export, the rest are hits — and the page swaps in the new curve layers. The λ and
time-step sliders re-run flow → select → export. Runs happen on one background thread
(:mod:`pipeline.serve_worker`); the page polls a JSON endpoint for its job.

The server reads and writes nothing outside FOLDER but the store (``store.path``, as for ``polyvec``):
a name that climbs out of the folder (``..``, an absolute path, a symbolic link out) is refused with a
403, an unknown drawing is a 404, a file that is not an image a 415, a malformed edit a 400; each is a
JSON ``{"error": "…"}`` (or a short page), and the server goes on.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import socket
import sys
from pathlib import Path, PurePosixPath

from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Route

from pipeline.engine.edits import edits_path_for
from pipeline.engine.execute.outputs import atomic_write
from pipeline.hydra_command import UsageError, is_override
from pipeline.inputs import IMAGE_SUFFIXES
from pipeline.serve_html import list_page, live_panel, live_script, message_page
from pipeline.serve_worker import Drawing, Runner

DEFAULT_PORT = 8765
THUMB_PX = 160
MAX_WAIT_S = 30.0


def drawing_of(runner: Runner, rel: str) -> Drawing:
    """The served drawing named ``rel`` (a path below the folder).

    Raises
    ------
    HTTPException
        403 for a name that climbs out of the folder, 415 for a file that is not an image, 404 for no
        such drawing.
    """
    parts = PurePosixPath(rel).parts
    if rel.startswith("/") or ".." in parts or "\\" in rel:
        raise HTTPException(403, f"{rel}: outside the served folder {runner.folder}")
    path = runner.folder / rel
    if not runner.inside(path):
        raise HTTPException(403, f"{rel}: a link out of the served folder {runner.folder}")
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise HTTPException(415, f"{rel}: not a drawing (images are {', '.join(sorted(s[1:] for s in IMAGE_SUFFIXES))})")
    drawing = runner.drawing(rel)
    if drawing is None:
        raise HTTPException(404, f"{rel}: no such drawing in {runner.folder}")
    return drawing


def float_param(value, name: str) -> float | None:
    """A flow setting from a request (None: the config's), or a 400."""
    if value is None or value == "":
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise HTTPException(400, f"{name} must be a number, got {value!r}") from None
    if not number > 0 and not (name == "lam" and number == 0):
        raise HTTPException(400, f"{name} must be positive, got {value!r}")
    return number


def write_edits(drawing: Drawing, doc) -> Path:
    """Check an edits document and write it as ``<stem>.keypoints.json`` beside the drawing.

    Raises
    ------
    HTTPException
        400 with the checker's one line when the document is not a valid edits file.
    """
    from stages.errors import InputError
    from stages.keypoint_edits import validate_edits

    if not isinstance(doc, dict):
        raise HTTPException(400, "edits must be a JSON object (the format of <stem>.keypoints.json)")
    try:
        validate_edits(doc)
    except InputError as exc:
        raise HTTPException(400, f"edits: {exc}") from None
    target = edits_path_for(drawing.path)
    atomic_write(target, json.dumps(doc, indent=1) + "\n")   # the worker may be reading the previous one
    return target


def create_app(runner: Runner) -> Starlette:
    """The web app over a :class:`~pipeline.serve_worker.Runner` (started by the caller)."""

    def index(request: Request):
        return HTMLResponse(list_page(str(runner.folder)))

    def drawings(request: Request):
        return JSONResponse({"folder": str(runner.folder), "drawings": runner.listing()})

    def thumbnail(request: Request):
        from PIL import Image, ImageOps

        drawing = drawing_of(runner, request.path_params["rel"])
        try:
            with Image.open(drawing.path) as img:
                img = ImageOps.exif_transpose(img)
                img.thumbnail((THUMB_PX, THUMB_PX))
                buf = io.BytesIO()
                img.convert("RGBA" if "A" in img.getbands() else "RGB").save(buf, format="PNG")
        except Exception as exc:   # an image PIL cannot open: the page says so in its status
            raise HTTPException(415, f"{drawing.rel}: cannot read as an image ({exc})") from None
        return Response(buf.getvalue(), media_type="image/png", headers={"Cache-Control": "no-cache"})

    def page(request: Request):
        from pipeline.page import page_data, render_html

        try:
            drawing = drawing_of(runner, request.path_params["rel"])
        except HTTPException as exc:
            return HTMLResponse(message_page("polyvec serve", exc.detail), status_code=exc.status_code)
        if drawing.state in ("queued", "running"):
            return HTMLResponse(message_page(drawing.rel, "waiting for its first run…", drawing.rel))
        q = request.query_params
        try:
            params = {"lam": float_param(q.get("lam"), "lam"), "dt": float_param(q.get("dt"), "dt")}
        except HTTPException as exc:
            return HTMLResponse(message_page(drawing.rel, exc.detail), status_code=400)
        job = runner.run_now(drawing, params)   # stored: a plan and hits; an edits file changed by hand: its re-run
        if job.state != "done" or "prep" not in job.keys:
            return HTMLResponse(message_page(drawing.rel, f"failed: {job.error or job.state}"), status_code=500)
        flow = runner.cfg.flow
        lam = params["lam"] if params["lam"] is not None else float(flow.lam)
        dt = params["dt"] if params["dt"] is not None else float(flow.dt)
        data = page_data(runner.store, job.keys, drawing.path)
        return HTMLResponse(render_html(data, live_panel(drawing.rel, lam, dt), live_script(drawing.rel)))

    async def run(request: Request):
        drawing = drawing_of(runner, request.path_params["rel"])
        try:
            body = json.loads(await request.body() or b"{}")
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise HTTPException(400, f"the request is not JSON ({exc})") from None
        if not isinstance(body, dict):
            raise HTTPException(400, "the request must be a JSON object")
        params = {"lam": float_param(body.get("lam"), "lam"), "dt": float_param(body.get("dt"), "dt")}
        if body.get("edits") is not None:
            write_edits(drawing, body["edits"])
        job = runner.submit([drawing], params, "edit", str(body.get("topology") or ""))
        return JSONResponse({"job": job.id})

    def job_status(request: Request):
        job = runner.job(request.path_params["job_id"])
        if job is None:
            raise HTTPException(404, f"no job {request.path_params['job_id']}")
        # ?wait=S answers when the job ends (at most S ≤ 30 s): no polls taking the GIL from the run
        wait = min(float_param(request.query_params.get("wait"), "wait") or 0.0, MAX_WAIT_S)
        job.finished.wait(wait)
        return JSONResponse(job.summary())

    def download(request: Request):
        drawing = drawing_of(runner, request.path_params["rel"])
        q = request.query_params
        bezier = q.get("bezier") in ("1", "true")
        params = {"lam": float_param(q.get("lam"), "lam"), "dt": float_param(q.get("dt"), "dt"), "bezier": bezier}
        job = runner.run_now(drawing, params)
        text = runner.export_text(job.keys, bezier) if job.state == "done" else None
        if text is None:
            raise HTTPException(500, f"{drawing.rel}: no SVG ({job.error or job.state})")
        name = PurePosixPath(drawing.rel).stem + (".bezier.svg" if bezier else ".svg")
        return Response(text, media_type="image/svg+xml",
                        headers={"Content-Disposition": f'attachment; filename="{name}"'})

    def error(request: Request, exc: Exception):
        status = exc.status_code if isinstance(exc, HTTPException) else 500
        detail = exc.detail if isinstance(exc, HTTPException) else f"{type(exc).__name__}: {exc}"
        return JSONResponse({"error": detail}, status_code=status)

    routes = [Route("/", index), Route("/api/drawings", drawings), Route("/thumb/{rel:path}", thumbnail),
              Route("/d/{rel:path}", page), Route("/api/run/{rel:path}", run, methods=["POST"]),
              Route("/api/job/{job_id:int}", job_status), Route("/svg/{rel:path}", download)]
    return Starlette(routes=routes, exception_handlers={HTTPException: error, Exception: error})


def parse_args(argv: list[str]) -> argparse.Namespace:
    """FOLDER, --port, --host and the trailing ``key=value`` overrides (exit 2 on a usage error)."""
    parser = argparse.ArgumentParser(
        prog="polyvec serve", usage="polyvec serve [FOLDER] [--port N] [--host H] [key=value ...]",
        epilog="key=value overrides change the config as for polyvec (store.path=, flow.lam= …).", description="Correct a folder's drawings in the browser: keypoint edits and flow "
        "settings re-run through the store and redraw in place.")
    parser.add_argument("folder", nargs="?", default=".", help="the drawings (searched recursively; default .)")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"default {DEFAULT_PORT}")
    parser.add_argument("--host", default="127.0.0.1", help="default 127.0.0.1 (this machine only)")
    # key=value overrides anywhere after the folder, told from paths as `polyvec` tells them
    overrides = [a for a in argv if is_override(a)]
    args = parser.parse_args([a for a in argv if a not in overrides])
    args.overrides = overrides
    if not Path(args.folder).is_dir():
        parser.error(f"{args.folder} is not a folder")
    return args


def main(argv: list[str] | None = None) -> None:
    """``polyvec serve``: exits 0 when stopped by Ctrl-C, 2 on a usage error."""
    import uvicorn

    from pipeline.engine.execute.process import quiet_full_collections, reuse_freed_memory

    args = parse_args(sys.argv[1:] if argv is None else argv)
    quiet_full_collections()   # as `polyvec`: the stages run in this process
    reuse_freed_memory()
    try:
        runner = Runner(Path(args.folder), args.overrides)
    except UsageError as exc:
        print(f"polyvec serve: error: {exc}", file=sys.stderr, flush=True)
        sys.exit(2)
    try:   # bound here, before any work: a port in use is one line, not uvicorn's log and traceback
        sock = socket.create_server((args.host, args.port), family=socket.AF_INET6 if ":" in args.host
                                    else socket.AF_INET)
    except OSError as exc:
        print(f"polyvec serve: error: cannot listen on {args.host}:{args.port} ({exc.strerror or exc})",
              file=sys.stderr, flush=True)
        sys.exit(2)
    runner.start()
    server = uvicorn.Server(uvicorn.Config(create_app(runner), log_level="warning", lifespan="off"))
    host = f"[{args.host}]" if ":" in args.host else args.host
    print(f"polyvec serve: {args.folder} at http://{host}:{sock.getsockname()[1]}/ (store {runner.store.url}; "
          "Ctrl-C stops)", flush=True)
    try:
        server.run(sockets=[sock])
    except KeyboardInterrupt:   # uvicorn shuts down on Ctrl-C, then raises it again
        pass
    print("polyvec serve: stopped", flush=True)
    sys.stdout.flush()
    # a batch may be running on the worker thread: leave without waiting for it (its artifacts are
    # written whole or not at all) and without the interpreter's teardown, as `polyvec` does
    os._exit(0 if server.started else 1)


if __name__ == "__main__":
    main()
