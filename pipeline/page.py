"""The inspection page of one drawing: a self-contained HTML file drawn from the artifact store.

``polyvec-inspect page IMAGE`` (and ``polyvec … runtime.pages=true``) writes it. The page needs no
server and no network: the drawing and the raster layers (narrow band, heatmaps) are embedded PNGs,
the vector layers (keypoints, frame-field crosses, traced graph, candidate paths, selected curves,
final curves and their ends) are SVG, and a small script does the toggling, the pan and zoom (wheel,
drag, up to 16×) and the keypoint editing: a click on the drawing adds a keypoint of the chosen type,
a click on one cycles its type (endpoint → junction → corner → removed); "save edits" downloads
``<stem>.keypoints.json`` (the format of :mod:`stages.keypoint_edits.stage`) and shows it in a text box.

To stay light on 1024-px drawings the field is drawn as at most ``MAX_CROSSES`` crosses on a grid,
heatmaps are rasterised at most ``HEATMAP_PX`` px on their long side, and coordinates are written
with one decimal.
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import numpy as np

from pipeline.engine.config import default_config
from pipeline.engine.lookup import STAGE_ORDER, planned_keys
from pipeline.engine.store import ArtifactStore
from stages.artifact import unpack_ragged
from stages.prep import internal_origin, internal_scale, source_size, to_internal
from stages.topology.topology_picture import TYPE_COLOURS

MAX_CROSSES = 2500
HEATMAP_PX = 512
TYPE_NAMES = {1: "endpoint", 3: "junction", 5: "corner"}


# -- pictures ------------------------------------------------------------------------------------
def _png_uri(img: np.ndarray) -> str:
    """``data:`` URI of a uint8 image (H, W), (H, W, 3) or (H, W, 4)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img)).save(buf, format="PNG", optimize=True)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _downsample(a: np.ndarray, max_px: int) -> np.ndarray:
    """Block-mean of a (H, W) array so its long side is at most ``max_px`` (ceil of the ratio)."""
    f = int(np.ceil(max(a.shape) / max_px))
    if f <= 1:
        return a
    h, w = a.shape
    pad = np.zeros((-(-h // f) * f, -(-w // f) * f), a.dtype)
    pad[:h, :w] = a
    return pad.reshape(pad.shape[0] // f, f, pad.shape[1] // f, f).max(axis=(1, 3))


def _rgba(alpha: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    a = (np.clip(alpha, 0, 1) * 255).astype(np.uint8)
    out = np.zeros(a.shape + (4,), np.uint8)
    out[..., :3] = colour
    out[..., 3] = a
    return out


def _polyline_d(curves) -> str:
    """SVG path data of several polylines (one decimal)."""
    parts = []
    for c in curves:
        c = np.asarray(c, np.float64).reshape(-1, 2)
        if len(c) < 2:
            continue
        parts.append("M" + " ".join(f"{x:.1f} {y:.1f}" for x, y in c))
    return " ".join(parts)


def _hex(c) -> str:
    return "#%02x%02x%02x" % tuple(int(v) for v in c[:3])


def field_crosses(roots: np.ndarray, mask: np.ndarray, max_crosses: int = MAX_CROSSES) -> tuple[str, str, int]:
    """Path data of the frame-field crosses on a grid over the band: (root 0 arms, root 1 arms, step).

    The grid step is the smallest ≥ 3 px giving at most ``max_crosses`` crosses; arms are
    ``0.45·step`` px long (root 1 scaled by its modulus relative to root 0).
    """
    mask = np.asarray(mask, bool)
    n = int(mask.sum())
    step = max(3, int(np.ceil(np.sqrt(max(n, 1) / max_crosses))))
    while True:
        sub = mask[::step, ::step]
        if sub.sum() <= max_crosses:
            break
        step += 1
    rr, cc = np.nonzero(sub)
    rr, cc = rr * step, cc * step
    r = np.asarray(roots)[rr, cc]
    m0 = np.abs(r[:, 0]) + 1e-12
    half = 0.45 * step
    out = []
    for k in (0, 1):
        d = r[:, k] / m0 if k else r[:, 0] / m0
        d = d * half
        cx, cy = cc + 0.5, rr + 0.5
        out.append(" ".join(f"M{x - dx:.1f} {y - dy:.1f}L{x + dx:.1f} {y + dy:.1f}"
                            for x, y, dx, dy in zip(cx, cy, d.real, d.imag)))
    return out[0], out[1], step


def _config_diff(stage: str, config: dict) -> dict:
    """Entries of a manifest's config that differ from ``conf/<stage>/default.yaml`` (dotted keys)."""
    defaults = default_config(stage)
    if stage == "keypoint_edits":
        e = config.get("edits") or {}
        out = {k: v for k, v in config.items() if k != "edits" and defaults.get(k) != v}
        if e:
            out["edits"] = f"+{len(e.get('added', []))} −{len(e.get('removed', []))} ~{len(e.get('retyped', []))}"
        return out

    def flat(d, prefix=""):
        items = {}
        for k, v in (d or {}).items():
            if isinstance(v, dict):
                items.update(flat(v, f"{prefix}{k}."))
            else:
                items[f"{prefix}{k}"] = v
        return items

    a, b = flat(config), flat(defaults)
    return {k: v for k, v in a.items() if b.get(k, object()) != v}


def curve_layers(store: ArtifactStore, keys: dict[str, str], prep_data: dict,
                 load=None) -> tuple[list[dict], dict]:
    """The layers a keypoint edit or a flow setting changes: candidate paths, selected curves, final
    curves and their ends (``{"id", "label", "svg", "on"}``, as in :func:`page_data`), and their counts.

    ``polyvec serve`` redraws these alone after a re-run (the drawing, heatmaps, field and graph stay).

    Parameters
    ----------
    store : ArtifactStore
    keys : dict
        Stage → key (the stages missing from it give no layer).
    prep_data : dict
        prep's ``data`` (the exported curves are mapped to the internal picture with it).
    load : callable, optional
        ``load(stage, key)`` → artifact; default ``store.load`` (a server passes its memo's).
    """
    load = load or store.load
    layers: list[dict] = []
    counts: dict = {}

    def add(layer_id: str, label: str, svg: str, on: bool = False) -> None:
        layers.append({"id": layer_id, "label": label, "svg": svg, "on": on})

    paths = []
    if "topology" in keys:
        topo = load("topology", keys["topology"])
        paths = topo.data.get("paths", [])
        add("candidates", "candidate paths", f'<path d="{_polyline_d([p["xy"] for p in paths])}" '
            f'stroke="#9467bd" stroke-opacity="0.6" stroke-width="1" vector-effect="non-scaling-stroke" fill="none"/>')
        counts["candidate_paths"] = len(paths)
    if "select" in keys and "flow" in keys:
        flow = load("flow", keys["flow"])
        curves = unpack_ragged(flow["curve_xy"], flow["curve_xy_offsets"])
        ids = {int(p["id"]): k for k, p in enumerate(paths)}
        chosen = load("select", keys["select"]).data.get("chosen", [])
        sel = [curves[ids.get(int(c), int(c))] for c in chosen if 0 <= ids.get(int(c), int(c)) < len(curves)]
        add("selected", "selected curves (flowed)", f'<path d="{_polyline_d(sel)}" stroke="#2ca02c" '
            f'stroke-width="2.5" stroke-opacity="0.7" vector-effect="non-scaling-stroke" fill="none"/>')
        counts["selected"] = len(sel)
    if "export" in keys:
        from pipeline.render import PALETTE

        ex = load("export", keys["export"]).data.get("curves", [])
        body, ends = [], []
        for i, c in enumerate(ex):
            pts = to_internal(c["points"], prep_data)  # exported in the drawing's pixels
            body.append(f'<path d="{_polyline_d([pts])}" stroke="{_hex(PALETTE[i % len(PALETTE)])}"/>')
            for j, p in ((0, pts[0]), (1, pts[-1])):
                t = int(c.get("end_types", [0, 0])[j])
                ends.append(f'<circle class="m" cx="{p[0]:.1f}" cy="{p[1]:.1f}" r="2" '
                            f'fill="{_hex(TYPE_COLOURS.get(t, (0, 0, 0)))}" stroke="#000"/>')
        add("curves", "final curves", '<g fill="none" stroke-width="2">' + "".join(body) + "</g>", True)
        add("ends", "curve end points", '<g stroke-width="0.6">'
            + "".join(ends) + "</g>", True)
        counts["curves"] = len(ex)
    return layers, counts


def page_data(store: ArtifactStore, keys: dict[str, str], image: str | Path) -> dict:
    """Everything the page shows, from the artifacts named by ``keys`` (stage → key).

    Returns
    -------
    dict
        ``width``, ``height`` (of the internal resolution), ``scale`` (internal pixels per drawing
        pixel: prep's supersampling), ``origin_x``, ``origin_y`` (the internal picture's corner in the
        drawing: prep's crop), ``pieces`` (a mosaic's, :func:`~stages.prep.internal_pieces`; [] if none), ``stem``, ``image``; ``layers``: list of ``{"id", "label", "svg",
        "on"}`` (SVG markup in image pixel coordinates); ``keypoints``: the editable points
        ``{"x", "y", "orig", "cur"}`` (``orig`` 0 = added, ``cur`` 0 = removed); ``stages``: the side
        panel rows; ``notes``: ``(stage, note)`` for what the stages said on the console (the sheet cut
        out of a photo, the parts laid side by side, the resampling: why the page shows what it shows);
        ``counts``.
    """
    image = Path(image)
    prep = store.load("prep", keys["prep"])
    grey = np.asarray(prep["grey"], np.float32)
    mask = np.asarray(prep["mask"], bool)
    h, w = grey.shape
    # A supersampled, downsampled or cropped prep: the page shows the internal picture; exported curves
    # and saved edits are in the drawing's pixels (internal = scale · (drawing − origin); in a mosaic of far-apart
    # parts, each piece's own offset: the page's toSource).
    scale = internal_scale(prep.data)
    layers: list[dict] = []

    def add(layer_id: str, label: str, svg: str, on: bool = False) -> None:
        layers.append({"id": layer_id, "label": label, "svg": svg, "on": on})

    def raster(img: np.ndarray, smooth: bool = False) -> str:
        rendering = "auto" if smooth else "pixelated"
        return (f'<image href="{_png_uri(img)}" x="0" y="0" width="{w}" height="{h}" '
                f'preserveAspectRatio="none" style="image-rendering:{rendering}"/>')

    add("drawing", "drawing", raster((np.clip(grey, 0, 1) * 255).astype(np.uint8)), True)
    add("band", "narrow band", raster(_rgba(mask * 0.45, (40, 110, 255))))
    counts: dict = {"band_pixels": int(mask.sum())}
    if "keypoints" in keys:
        kp = store.load("keypoints", keys["keypoints"])
        hm = np.asarray(kp["heatmaps"], np.float32)
        add("h1", "heatmap: detection", raster(_rgba(_downsample(hm[0], HEATMAP_PX) * 0.9, (230, 20, 20)), True))
        cls = np.stack([_downsample(hm[i], HEATMAP_PX) for i in (1, 2, 3)])
        best = cls.argmax(0)
        rgba = np.zeros(best.shape + (4,), np.uint8)
        for i, t in enumerate((1, 3, 5)):
            rgba[best == i, :3] = TYPE_COLOURS[t]
        rgba[..., 3] = (np.clip(cls.max(0), 0, 1) * 200).astype(np.uint8)
        add("hclass", "heatmaps: classes", raster(rgba, True))
    if "field" in keys:
        field = store.load("field", keys["field"])
        d0, d1, step = field_crosses(field["roots"], mask)
        add("field", f"frame field (every {step} px)",
            f'<path d="{d0}" stroke="#d62728" stroke-width="1" vector-effect="non-scaling-stroke" fill="none"/>'
            f'<path d="{d1}" stroke="#1f77b4" stroke-width="1" vector-effect="non-scaling-stroke" fill="none"/>')
    if "graph" in keys:
        g = store.load("graph", keys["graph"])
        xy = np.asarray(g["vertex_xy"], np.float64).reshape(-1, 2)
        e = np.asarray(g["edges"]).reshape(-1, 2)
        d = " ".join(f"M{xy[a, 0]:.1f} {xy[a, 1]:.1f}L{xy[b, 0]:.1f} {xy[b, 1]:.1f}" for a, b in e)
        add("graph", "traced graph", f'<path d="{d}" stroke="#2a5ad7" stroke-width="1" '
            f'vector-effect="non-scaling-stroke" fill="none"/>')
        counts["graph_vertices"], counts["graph_edges"] = len(xy), len(e)
    curves, curve_counts = curve_layers(store, keys, prep.data)
    layers += curves
    counts.update(curve_counts)
    kps = []
    if "keypoints" in keys:
        det = store.load("keypoints", keys["keypoints"]).data.get("points", [])
        kps = [{"x": round(p["x"], 2), "y": round(p["y"], 2), "orig": int(p["type"]), "cur": int(p["type"])}
               for p in det]
        if "keypoint_edits" in keys:
            for e in store.load("keypoint_edits", keys["keypoint_edits"]).data.get("edits", []):
                if e["op"] == "added":
                    kps.append({"x": e["x"], "y": e["y"], "orig": 0, "cur": int(e["type"])})
                elif e["op"] == "removed":
                    kps[e["keypoint"]]["cur"] = 0
                else:
                    kps[e["keypoint"]]["cur"] = int(e["type"])
        counts["keypoints"] = {TYPE_NAMES[t]: sum(p["cur"] == t for p in kps) for t in (1, 3, 5)}
    rows, notes = [], []
    for stage in STAGE_ORDER:   # the DAG's order
        if stage not in keys:
            continue
        m = store.manifest(stage, keys[stage])
        notes += [(stage, note) for note in m.get("warnings", [])]
        rows.append({"stage": stage, "key": keys[stage][:12], "seconds": m.get("duration_s"),
                     "peak_mb": m.get("peak_rss_mb"), "config": _config_diff(stage, m.get("config", {}))})
    source_h, source_w = source_size(prep.data, (h, w))
    ox, oy = map(float, internal_origin(prep.data))
    return {"width": w, "height": h, "scale": scale, "origin_x": ox, "origin_y": oy,
            "pieces": prep.data.get("pieces") or [],
            "source_width": source_w, "source_height": source_h,
            "stem": image.stem, "image": str(image), "layers": layers,
            "keypoints": kps, "stages": rows, "notes": notes, "counts": counts}


# -- HTML --------------------------------------------------------------------------------------
_CSS = """
*{box-sizing:border-box}body{margin:0;font:13px system-ui,sans-serif;display:flex;height:100vh;overflow:hidden}
#side{width:380px;overflow:auto;padding:8px 10px;border-right:1px solid #ccc;background:#fafafa}
#main{flex:1;position:relative;background:#fff}#view path,#view circle.m{vector-effect:non-scaling-stroke}#view{width:100%;height:100%;display:block;cursor:crosshair}
h1{font-size:15px;margin:4px 0 8px}ul{margin:2px 0;padding-left:16px;font-size:11px}h2{font-size:13px;margin:12px 0 4px}label{display:block;margin:2px 0}
table{border-collapse:collapse;font-size:11px}td,th{border-bottom:1px solid #ddd;padding:2px 4px;text-align:left;
vertical-align:top}code{font-size:11px}textarea{width:100%;height:120px;font-size:11px}
.kp{stroke:#000;stroke-width:1px;vector-effect:non-scaling-stroke;cursor:pointer}.kp.t0{fill:none;stroke:#888;
stroke-dasharray:2 2}.kp.added{stroke:#f0f;stroke-width:2px}#zoom{position:absolute;right:8px;top:8px;
background:#fffc;padding:2px 6px;border:1px solid #ccc}
"""

_JS = r"""
(function(){
const D=JSON.parse(document.getElementById('pv-data').textContent);
const W=D.width,H=D.height,S=D.scale||1,OX=D.origin_x||0,OY=D.origin_y||0,svg=document.getElementById('view'),kpg=document.getElementById('kp-layer');
function toSource(x,y){x/=S;y/=S;const P=D.pieces||[];if(!P.length)return[x+OX,y+OY];let k=0,best=Infinity;
 P.forEach((q,i)=>{const dx=Math.max(q[0]-x,0,x-q[0]-q[4]),dy=Math.max(q[1]-y,0,y-q[1]-q[5]),d=dx*dx+dy*dy;if(d<best){best=d;k=i}});
 return[x-P[k][0]+P[k][2],y-P[k][1]+P[k][3]]}
const COL={1:'#1e5aff',3:'#ff8c00',5:'#00aa3c',0:'none'},NAME={1:'endpoint',3:'junction',5:'corner'};
const CYCLE={1:3,3:5,5:0,0:1};let vb={x:0,y:0,w:W,h:H};const pts=D.keypoints;
function scale(){const m=svg.getScreenCTM();return m?m.a:1}
function fitScale(){return Math.min(svg.clientWidth/W,svg.clientHeight/H)}
function setVB(){svg.setAttribute('viewBox',vb.x+' '+vb.y+' '+vb.w+' '+vb.h);
 const s=scale(),r=5/s;document.querySelectorAll('circle.kp').forEach(c=>c.setAttribute('r',r));
 document.querySelectorAll('circle.m').forEach(c=>c.setAttribute('r',2.5/s));
 document.getElementById('zoom').textContent=(s/fitScale()).toFixed(1)+'×';}
function toSvg(cx,cy){const p=svg.createSVGPoint();p.x=cx;p.y=cy;return p.matrixTransform(svg.getScreenCTM().inverse())}
function toScreen(x,y){const p=svg.createSVGPoint();p.x=x;p.y=y;const q=p.matrixTransform(svg.getScreenCTM());return {x:q.x,y:q.y}}
function zoomAt(cx,cy,f){const p=toSvg(cx,cy);let nw=Math.min(Math.max(vb.w/f,W/16),W*1.5);const k=nw/vb.w;
 vb={x:p.x-(p.x-vb.x)*k,y:p.y-(p.y-vb.y)*k,w:nw,h:vb.h*k};setVB()}
function draw(){kpg.textContent='';const s=scale();pts.forEach((p,i)=>{
 const c=document.createElementNS('http://www.w3.org/2000/svg','circle');c.setAttribute('cx',p.x);c.setAttribute('cy',p.y);
 c.setAttribute('r',5/s);c.setAttribute('class','kp t'+p.cur+(p.orig===0?' added':'')+' ty'+p.cur);c.setAttribute('fill',COL[p.cur]);
 c.dataset.i=i;const t=document.createElementNS('http://www.w3.org/2000/svg','title');
 t.textContent=(p.cur?NAME[p.cur]:'removed')+' ('+p.x.toFixed(1)+', '+p.y.toFixed(1)+')'+(p.orig===0?' added':p.orig!==p.cur?' was '+NAME[p.orig]:'');
 c.appendChild(t);kpg.appendChild(c)});typeVis();count()}
function typeVis(){[1,3,5].forEach(t=>{const on=document.getElementById('show-t'+t).checked;
 kpg.querySelectorAll('.ty'+t).forEach(c=>c.style.display=on?'':'none')})}
function edits(){const r={format:'polyvec-keypoint-edits',version:1,image:D.image.split(/[\\/]/).pop(),width:D.source_width,
 height:D.source_height,added:[],removed:[],retyped:[]};pts.forEach(p=>{const[x,y]=toSource(p.x,p.y);
 if(p.orig===0){if(p.cur)r.added.push({x:+x.toFixed(1),y:+y.toFixed(1),type:NAME[p.cur]})}
 else if(p.cur===0)r.removed.push({x:x,y:y});else if(p.cur!==p.orig)r.retyped.push({x:x,y:y,type:NAME[p.cur]})});return r}
function count(){const e=edits();document.getElementById('edit-count').textContent=
 e.added.length+' added, '+e.removed.length+' removed, '+e.retyped.length+' retyped'}
function click(cx,cy,target){if(target&&target.classList&&target.classList.contains('kp')){const i=+target.dataset.i,p=pts[i];
  p.cur=CYCLE[p.cur];if(p.orig===0&&p.cur===0)pts.splice(i,1);draw();edited();return}
 const q=toSvg(cx,cy);if(q.x<0||q.y<0||q.x>W||q.y>H)return;
 const t=+document.querySelector('input[name=addtype]:checked').value;pts.push({x:q.x,y:q.y,orig:0,cur:t});draw();edited()}
function edited(){const f=window.polyvecPage.onEdit;if(f)f()}
function save(){const text=JSON.stringify(edits(),null,1);document.getElementById('edits-json').value=text;
 const a=document.createElement('a');a.href=URL.createObjectURL(new Blob([text],{type:'application/json'}));
 a.download=D.stem+'.keypoints.json';document.body.appendChild(a);a.click();a.remove();
 document.getElementById('saved').textContent='saved '+D.stem+'.keypoints.json (put it beside '+D.image+')'}
let drag=null;svg.addEventListener('pointerdown',e=>{drag={x:e.clientX,y:e.clientY,vb:{...vb},moved:false,t:e.target}});
svg.addEventListener('pointermove',e=>{if(!drag||!(e.buttons&1))return;const dx=e.clientX-drag.x,dy=e.clientY-drag.y;
 if(Math.abs(dx)+Math.abs(dy)>4)drag.moved=true;if(!drag.moved)return;const s=scale();
 vb={...drag.vb,x:drag.vb.x-dx/s,y:drag.vb.y-dy/s};setVB()});
svg.addEventListener('pointerup',e=>{if(drag&&!drag.moved)click(e.clientX,e.clientY,drag.t);drag=null});
svg.addEventListener('wheel',e=>{e.preventDefault();zoomAt(e.clientX,e.clientY,Math.exp(-e.deltaY*0.0015))},{passive:false});
document.querySelectorAll('input.layer').forEach(cb=>cb.addEventListener('change',()=>{
 document.getElementById('layer-'+cb.dataset.layer).style.display=cb.checked?'':'none'}));
[1,3,5].forEach(t=>document.getElementById('show-t'+t).addEventListener('change',typeVis));
document.getElementById('save').addEventListener('click',save);
document.getElementById('fit').addEventListener('click',()=>{vb={x:0,y:0,w:W,h:H};setVB()});
document.getElementById('zin').addEventListener('click',()=>{const r=svg.getBoundingClientRect();zoomAt(r.x+r.width/2,r.y+r.height/2,2)});
document.getElementById('zout').addEventListener('click',()=>{const r=svg.getBoundingClientRect();zoomAt(r.x+r.width/2,r.y+r.height/2,0.5)});
window.addEventListener('resize',setVB);
window.polyvecPage={data:D,toScreen,edits,points:pts,zoomAt,draw,onEdit:null,setView:(x,y,w)=>{vb={x:x,y:y,w:w,h:w*H/W};setVB()}};
draw();setVB();
})();
"""


def render_html(data: dict, live_panel: str = "", live_script: str = "") -> str:
    """The page's HTML text from :func:`page_data`.

    ``live_panel`` (HTML, at the top of the side panel) and ``live_script`` (run after the page's own
    script, which sets ``polyvecPage.onEdit`` hooks) are ``polyvec serve``'s additions; the static page
    has neither. The static page's "save edits" box is hidden on a live page: the server writes each
    edit itself.
    """
    esc = html.escape
    w, h = data["width"], data["height"]
    hidden = ' style="display:none"'
    layer_svg = "".join(f'<g id="layer-{L["id"]}"{"" if L["on"] else hidden}>{L["svg"]}</g>' for L in data["layers"])
    toggles = "".join(f'<label><input type="checkbox" class="layer" id="toggle-{L["id"]}" data-layer="{L["id"]}"'
                      f'{" checked" if L["on"] else ""}> {esc(L["label"])}</label>' for L in data["layers"])
    toggles += '<label><input type="checkbox" class="layer" id="toggle-kp" data-layer="kp" checked> keypoints</label>'
    kp_types = "".join(f'<label style="display:inline;margin-right:8px"><input type="checkbox" id="show-t{t}" checked>'
                       f'<span style="color:{_hex(TYPE_COLOURS[t])}">●</span> {n}s</label>'
                       for t, n in TYPE_NAMES.items())
    add_types = "".join(f'<label style="display:inline;margin-right:8px"><input type="radio" name="addtype" '
                        f'id="add-t{t}" value="{t}"{" checked" if t == 1 else ""}> {n}</label>'
                        for t, n in TYPE_NAMES.items())
    rows = "".join(
        f'<tr><td>{esc(r["stage"])}</td><td><code>{esc(r["key"])}</code></td><td>{r["seconds"] or 0:.2f}</td>'
        f'<td>{r["peak_mb"] or ""}</td><td><code>{esc(json.dumps(r["config"], ensure_ascii=False)) if r["config"] else "defaults"}'
        f'</code></td></tr>' for r in data["stages"])
    notes = "".join(f"<li><b>{esc(stage)}</b>: {esc(note)}</li>" for stage, note in data.get("notes", []))
    notes = f'<h2>what was done to the drawing</h2><ul id="notes">{notes}</ul>' if notes else ""
    counts = "".join(f"<tr><td>{esc(k)}</td><td>{esc(json.dumps(v) if isinstance(v, dict) else str(v))}</td></tr>"
                     for k, v in data["counts"].items())
    payload = json.dumps({k: data[k] for k in ("width", "height", "scale", "origin_x", "origin_y", "pieces", "source_width",
                                                 "source_height", "stem", "image", "keypoints")})
    payload = payload.replace("</", "<\\/")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>polyvec: {esc(data["stem"])}</title><style>{_CSS}</style></head>
<body><div id="side"><h1>polyvec · {esc(data["stem"])} <small>({w}×{h})</small></h1>
<div><code>{esc(data["image"])}</code></div>{live_panel}{notes}
<h2>layers</h2>{toggles}<div>{kp_types}</div>
<div style="margin-top:6px"><button id="fit">fit</button> <button id="zin">zoom +</button>
<button id="zout">zoom −</button> <small>wheel: zoom · drag: pan</small></div>
<h2>keypoint edits</h2><div><small>click the drawing: add a</small></div><div>{add_types}</div>
<div><small>click a keypoint: endpoint → junction → corner → removed</small></div>
<div id="edit-count"></div><div id="static-save"{hidden if live_panel else ""}><button id="save">save edits</button> <span id="saved"></span>
<textarea id="edits-json" readonly placeholder="the edits JSON appears here on save (copy it to {esc(data["stem"])}.keypoints.json)"></textarea>
<div><small>then: <code>polyvec input={esc(data["image"])}</code> picks up <code>{esc(data["stem"])}.keypoints.json</code>
beside it (or <code>keypoint_edits.file=…</code>)</small></div></div>
<h2>stages</h2><table id="stages"><tr><th>stage</th><th>key</th><th>s</th><th>peak MB</th><th>config ≠ default</th></tr>{rows}</table>
<h2>counts</h2><table id="counts">{counts}</table></div>
<div id="main"><svg id="view" xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {w} {h}" preserveAspectRatio="xMidYMid meet">
{layer_svg}<g id="layer-kp"><g id="kp-layer"></g></g></svg><div id="zoom"></div></div>
<script type="application/json" id="pv-data">{payload}</script>
<script>{_JS}</script>{f"<script>{live_script}</script>" if live_script else ""}</body></html>
"""


def write_page(store: ArtifactStore, image: str | Path, out: str | Path, keys: dict[str, str] | None = None) -> Path:
    """Write the inspection page of ``image``.

    Parameters
    ----------
    store : ArtifactStore
    image : path
        The input drawing.
    out : path
        The HTML file to write.
    keys : dict, optional
        Stage → key of the artifacts to draw (a batch's); default: :func:`planned_keys` (those of the
        default config, else the newest stored).
    """
    keys = keys if keys is not None else planned_keys(store, image)
    if "prep" not in keys:
        raise LookupError(f"no prep artifact for {image} in {store.url}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = render_html(page_data(store, keys, image))
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(out)
    return out


def write_pages(batch, store: ArtifactStore, out_dir: str | Path) -> list[Path]:
    """``OUTPUT/<name>.html`` for every image of a batch with stored artifacts, named like its SVG."""
    written = []
    for image, per in batch.results.items():
        keys = batch.keys(image)
        if "prep" not in keys:
            continue
        files = batch.outputs.get(image)
        name = Path(files[0]).stem if files else Path(image).stem
        written.append(write_page(store, image, Path(out_dir) / f"{name}.html", keys))
    return written
