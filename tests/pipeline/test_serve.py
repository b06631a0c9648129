"""``polyvec serve``: the server as a user starts it (a subprocess), its refusals over plain HTTP, and a
keypoint edit and a λ change round trip in headless Chromium.

One server runs for the module, on a folder holding the bundled example drawing, a file that is not
an image, an image that cannot be read and a symbolic link out of the folder.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.pipeline.cdp import chromium_path

needs_chromium = pytest.mark.skipif(
    chromium_path() is None,
    reason="chromium is not installed (Debian package `chromium`; .ci/run installs it with apt-get)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get(url: str, data: bytes | None = None) -> tuple[int, bytes]:
    """Status and body of a request (an HTTP error is an answer too)."""
    try:
        with urllib.request.urlopen(urllib.request.Request(url, data=data), timeout=30) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """``polyvec serve FOLDER --port P store.path=…`` running; yields (base URL, folder, process)."""
    from stages.synthetic import example_drawing

    work = tmp_path_factory.mktemp("serve")
    folder = work / "drawings"
    (folder / "sub").mkdir(parents=True)
    (folder / "sub" / "example.png").write_bytes(example_drawing().png_bytes())
    (folder / "notes.txt").write_text("not a drawing")
    (folder / "broken.png").write_bytes(b"not a png at all")
    (work / "outside.png").write_bytes(example_drawing().png_bytes())
    (folder / "escape.png").symlink_to(work / "outside.png")
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.launch", "serve", str(folder), "--port", str(port),
                             f"store.path={work / 'store'}"], cwd=work, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    base = f"http://127.0.0.1:{port}"
    deadline = time.time() + 120
    while True:
        try:
            if get(base + "/api/drawings")[0] == 200:
                break
        except OSError:
            pass
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"polyvec serve did not start: {proc.stdout.read()[-2000:]}")
        time.sleep(0.2)
    yield base, folder, proc
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


def wait_done(base: str, timeout: float = 300) -> dict:
    """The drawings' states once none is queued or running."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        listing = json.loads(get(base + "/api/drawings")[1])
        if all(d["state"] in ("done", "failed") for d in listing["drawings"]):
            return {d["path"]: d for d in listing["drawings"]}
        time.sleep(0.3)
    pytest.fail("the first runs did not finish")


def test_overrides_after_the_folder_and_the_defaults(tmp_path):
    from pipeline.serve import parse_args

    args = parse_args([str(tmp_path), "flow.lam=0.5", "--port", "9000", "store.path=x"])
    assert (args.folder, args.port, args.host) == (str(tmp_path), 9000, "127.0.0.1")
    assert args.overrides == ["flow.lam=0.5", "store.path=x"]
    assert parse_args(["flow.lam=1"]).folder == "."   # no folder: the current one
    with pytest.raises(SystemExit) as exc:
        parse_args([str(tmp_path / "missing")])
    assert exc.value.code == 2


@pytest.mark.slow
def test_listens_on_localhost_only_by_default(server):
    base, folder, proc = server
    port = int(base.rsplit(":", 1)[1])
    listening = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if Path(table).is_file():
            for line in Path(table).read_text().splitlines()[1:]:
                local, state = line.split()[1], line.split()[3]
                if state == "0A" and int(local.rsplit(":", 1)[1], 16) == port:   # 0A: LISTEN
                    listening.append(local.rsplit(":", 1)[0])
    assert listening == ["0100007F"], listening   # 127.0.0.1, and nothing else


@pytest.mark.slow
def test_bad_requests_are_clear_errors_and_the_server_goes_on(server):
    base, folder, proc = server
    states = wait_done(base)
    # found as `polyvec FOLDER` finds images; the link out of the folder is never listed
    assert set(states) == {"sub/example.png", "broken.png"}
    assert states["sub/example.png"]["state"] == "done"
    assert states["broken.png"]["state"] == "failed" and "prep" in states["broken.png"]["error"]
    cases = [("/d/..%2F..%2Fetc%2Fpasswd", None, 403, "outside the served folder"),
             ("/svg//etc/passwd", None, 403, "outside the served folder"),
             ("/api/run/..%2Foutside.png", b"{}", 403, "outside the served folder"),
             ("/thumb/escape.png", None, 403, "a link out of the served folder"),
             ("/api/run/notes.txt", b"{}", 415, "notes.txt: not a drawing"),
             ("/svg/nope.png", None, 404, "nope.png: no such drawing"),
             ("/api/run/sub/example.png", b"{not json", 400, "the request is not JSON"),
             ("/api/run/sub/example.png", json.dumps({"edits": {"added": [{"x": 3, "y": 4, "type": "tee"}]}}).encode(),
              400, "edits: added[0]: type must be endpoint, junction or corner (or 1, 3, 5), got 'tee'"),
             ("/api/run/sub/example.png", b'{"lam": "much"}', 400, "lam must be a number"),
             ("/api/job/99999", None, 404, "no job 99999")]
    for path, data, status, said in cases:
        code, body = get(base + path, data)
        assert code == status, (path, code, body[:300])
        if path.startswith("/d/"):
            assert said in body.decode()        # a page: the message in it
        else:
            assert said in json.loads(body)["error"], (path, body)
    assert not (folder / "sub" / "example.keypoints.json").exists()   # a refused edit writes nothing
    # an edits file spoilt by hand beside the drawing: the re-run fails with the command line's message
    (folder / "sub" / "example.keypoints.json").write_text("{not json")
    code, body = get(base + "/api/run/sub/example.png", b'{"lam": 2.5}')
    assert code == 200
    job = json.loads(get(base + f"/api/job/{json.loads(body)['job']}?wait=30")[1])
    assert job["state"] == "failed" and "example.keypoints.json: not JSON" in job["error"], job
    (folder / "sub" / "example.keypoints.json").unlink()
    # the failed drawing's page says why; the server still answers
    code, body = get(base + "/d/broken.png")
    assert code == 500 and b"failed: prep" in body
    assert get(base + "/api/drawings")[0] == 200 and proc.poll() is None
    # downloads: the SVG and, via export.bezier=true, the Bézier SVG
    code, svg = get(base + "/svg/sub/example.png")
    assert code == 200 and svg.count(b"<path") > 3
    code, bezier = get(base + "/svg/sub/example.png?bezier=1")
    assert code == 200 and bezier != svg and b"<path" in bezier


README_HEADING = "## Correcting in the browser: polyvec serve"


def _serve_until_done(args: list[str], cwd: Path) -> str:
    """Run a ``polyvec serve`` command line until its drawings are done, then Ctrl-C it; its output."""
    port = int(args[args.index("--port") + 1]) if "--port" in args else 8765
    with socket.socket() as s:
        if s.connect_ex(("127.0.0.1", port)) == 0:
            pytest.skip(f"port {port} of the README's command is taken on this machine")
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.launch", *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        deadline = time.time() + 120
        while True:
            try:
                states = wait_done(f"http://127.0.0.1:{port}", timeout=300)
                break
            except (OSError, json.JSONDecodeError):
                assert proc.poll() is None and time.time() < deadline, f"{args}: no server"
                time.sleep(0.3)
        assert states and all(d["state"] == "done" for d in states.values()), states
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out[-2000:]
    return out


@pytest.mark.slow
def test_the_readme_commands_run(tmp_path):
    """The README section's ```bash block, as written, in a folder with a ``scans/`` of one drawing."""
    from stages.synthetic import example_drawing

    from tests.conftest import REPO, run_cli

    readme = (REPO / "README.md").read_text()
    if README_HEADING not in readme:
        pytest.skip(f"README.md has no '{README_HEADING}' section yet")
    block = readme.split(README_HEADING, 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    commands = [ln.split("  #", 1)[0].split() for ln in block.splitlines() if ln.split("  #", 1)[0].strip()]
    assert commands and commands[0][:2] == ["polyvec", "serve"]
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "cat.png").write_bytes(example_drawing().png_bytes())
    for prog, *args in commands:
        assert prog == "polyvec", prog
        if args[:1] == ["serve"]:
            assert "polyvec serve: stopped" in _serve_until_done(args, tmp_path)
        else:
            r = run_cli(*args, cwd=tmp_path)
            assert r.returncode == 0, f"{args}: {r.stderr[-1500:]}"


def _curves(browser) -> str:
    return browser.eval("document.getElementById('layer-curves').innerHTML")


def _wait(browser, expression: str, timeout: float = 120) -> None:
    deadline = time.time() + timeout
    while not browser.eval(expression):
        if time.time() > deadline:
            raise TimeoutError(f"{expression}: {browser.eval('window.polyvecLive && polyvecLive.status')}")
        time.sleep(0.1)


@pytest.mark.slow
@needs_chromium
def test_browser_edit_a_keypoint_and_lambda_redraw_in_place(server):
    pytest.importorskip("websocket", reason="websocket-client is not installed (the `test` extra)")
    from tests.pipeline.cdp import Browser

    base, folder, proc = server
    wait_done(base)
    edits_file = folder / "sub" / "example.keypoints.json"
    browser = Browser()
    try:
        browser.open(base + "/", ready="window.polyvecList !== undefined && !!document.querySelector('a[href^=\"/d/\"]')")
        assert "sub/example.png" in browser.eval("document.getElementById('rows').textContent")
        _wait(browser, "Array.from(document.images).some(i => i.complete && i.naturalWidth > 0)", 30)   # a thumbnail
        browser.open(base + browser.eval("document.querySelector('a[href=\"/d/sub/example.png\"]').getAttribute('href')"),
                     ready="window.polyvecLive !== undefined")
        before = _curves(browser)
        assert before.count("<path") > 3
        # the server writes each edit: the static page's "save edits" box is not shown
        assert browser.eval("document.getElementById('save').offsetParent === null")
        # zoom in; the view must stay through the redraws
        browser.eval("polyvecPage.setView(60, 40, 150)")
        view = browser.eval("document.getElementById('view').getAttribute('viewBox')")
        # the middle vertex of the longest curve: a point on a stroke
        x, y = browser.eval("""(() => {let best = null;
            document.querySelectorAll('#layer-curves path').forEach(p => {const n = p.getAttribute('d').split(' ');
              if (!best || n.length > best.length) best = n});
            const k = Math.floor(best.length / 4) * 2; return [+best[k].replace('M', ''), +best[k + 1]]})()""")
        browser.eval(f"polyvecPage.setView({x - 75}, {y - 55}, 150)")
        view = browser.eval("document.getElementById('view').getAttribute('viewBox')")
        browser.command("Input.dispatchKeyEvent", type="keyDown", key="j", text="j")   # the junction shortcut
        browser.command("Input.dispatchKeyEvent", type="keyUp", key="j")
        assert browser.eval("document.getElementById('add-t3').checked")
        sx, sy = browser.eval(f"(() => {{const p = polyvecPage.toScreen({x}, {y}); return [p.x, p.y]}})()")
        browser.click(sx, sy)
        _wait(browser, "polyvecLive.redraws === 1")
        after_edit = _curves(browser)
        assert after_edit != before
        assert browser.eval("document.getElementById('view').getAttribute('viewBox')") == view
        saved = json.loads(edits_file.read_text())
        assert saved == browser.eval("polyvecPage.edits()")   # the static page's "save edits" document
        (added,) = saved["added"]
        assert added["type"] == "junction" and saved["removed"] == saved["retyped"] == []
        # λ: set the slider and let it go
        browser.eval("(() => {const s = document.getElementById('lam'); s.value = 1;"
                     "s.dispatchEvent(new Event('input')); s.dispatchEvent(new Event('change'))})()")
        _wait(browser, "polyvecLive.redraws === 2")
        after_lam = _curves(browser)
        assert after_lam != after_edit
        assert browser.eval("document.getElementById('view').getAttribute('viewBox')") == view
        assert "lam=1" in browser.eval("document.getElementById('dl-svg').getAttribute('href')")
        # undo (ctrl-z): the junction goes, the edits file says so
        browser.command("Input.dispatchKeyEvent", type="keyDown", key="z", modifiers=2)   # 2: ctrl
        _wait(browser, "polyvecLive.redraws === 3")
        assert json.loads(edits_file.read_text())["added"] == []
    finally:
        browser.close()
    # Ctrl-C: one line, exit 0
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out[-2000:]
    assert out.strip().splitlines()[-1] == "polyvec serve: stopped"
