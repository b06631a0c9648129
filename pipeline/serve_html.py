"""``polyvec serve``'s HTML: the folder's list, the live additions to the inspection page, short pages.

The drawing page is the inspection page of :mod:`pipeline.page` with a panel (status, λ and time-step
sliders, undo, downloads) and a script that sends every keypoint edit to the server, polls its job
and swaps the curve layers in place: the view box is not touched, so pan and zoom stay.
"""

from __future__ import annotations

import html
import json
from urllib.parse import quote

_LIST_CSS = """body{font:14px system-ui,sans-serif;margin:16px}table{border-collapse:collapse}
td,th{padding:4px 8px;border-bottom:1px solid #ddd;text-align:left;vertical-align:middle}
img{max-width:120px;max-height:90px;background:#fff;border:1px solid #ccc}.failed{color:#b00}.done{color:#070}
#error{color:#b00}"""

_LIST_JS = r"""
(function(){
const rows=document.getElementById('rows');let shown='';
function row(d){const u=d.path.split('/').map(encodeURIComponent).join('/');
 const st=d.state==='running'?'running: '+d.done+' of '+d.stages+' stages'+(d.stage?' ('+d.stage+')':''):d.state;
 return '<tr data-path="'+d.path.replace(/"/g,'&quot;')+'"><td><img src="/thumb/'+u+'" alt=""></td>'+
  '<td><a href="/d/'+u+'">'+d.path.replace(/</g,'&lt;')+'</a></td><td class="'+d.state+'">'+st+
  (d.error?': '+d.error.replace(/</g,'&lt;'):'')+'</td></tr>'}
async function poll(){try{const r=await fetch('/api/drawings');const j=await r.json();
 const html=j.drawings.length?j.drawings.map(row).join(''):'<tr><td colspan=3>no drawings in this folder</td></tr>';
 if(html!==shown){rows.innerHTML=html;shown=html}  // unchanged rows keep their loaded thumbnails
 document.getElementById('error').textContent='';window.polyvecList=j}
 catch(e){document.getElementById('error').textContent='the server does not answer ('+e+')'}
 setTimeout(poll,1000)}
poll()})();
"""


def list_page(folder: str) -> str:
    """The folder's drawings: thumbnail, name (a link to its page) and status, polled every second."""
    esc = html.escape(folder)
    return f"""<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>polyvec serve: {esc}</title>
<style>{_LIST_CSS}</style></head><body><h1>polyvec · {esc}</h1><div id="error"></div>
<table><thead><tr><th></th><th>drawing</th><th>status</th></tr></thead><tbody id="rows"></tbody></table>
<script>{_LIST_JS}</script></body></html>"""


def message_page(title: str, text: str, poll_path: str | None = None) -> str:
    """A short page: an error, or a drawing still running (``poll_path``: reload once it is done)."""
    script = ""
    if poll_path is not None:
        script = f"""<script>(async function wait(){{const r=await fetch('/api/drawings');const j=await r.json();
const d=j.drawings.find(x=>x.path==={json.dumps(poll_path)});
if(d&&d.state!=='queued'&&d.state!=='running'){{location.reload();return}}
if(d)document.getElementById('msg').textContent=d.state+(d.state==='running'?': '+d.done+' of '+d.stages+' stages':'');
setTimeout(wait,500)}})()</script>"""
    return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title></head>'
            f'<body style="font:14px system-ui,sans-serif;margin:16px"><p><a href="/">all drawings</a></p>'
            f'<h1>{html.escape(title)}</h1><p id="msg">{html.escape(text)}</p>{script}</body></html>')


def live_panel(rel: str, lam: float, dt: float) -> str:
    """The side panel's live controls (first in it): status, sliders, undo, downloads."""
    u = html.escape(quote(rel))
    return f"""<div id="live" style="margin:6px 0;padding:6px;border:1px solid #ccc;background:#fff">
<div><a href="/">all drawings</a> · <a id="dl-svg" href="/svg/{u}?lam={lam}&amp;dt={dt}" download>SVG</a> ·
<a id="dl-bezier" href="/svg/{u}?bezier=1&amp;lam={lam}&amp;dt={dt}" download>Bézier SVG</a></div>
<label>λ <code>flow.lam</code> <input type="range" id="lam" min="0" max="10" step="0.1" value="{lam}">
<output id="lam-value">{lam}</output></label>
<label>time step <code>flow.dt</code> <input type="range" id="dt" min="0.001" max="0.03" step="0.001" value="{dt}">
<output id="dt-value">{dt}</output></label>
<div><button id="undo">undo (ctrl-z)</button> <small>keys: e endpoint · j junction · c corner</small></div>
<div id="live-status" style="min-height:1.3em"></div></div>"""


_LIVE_JS = r"""
(function(){
const P=window.polyvecPage,REL=%(rel)s,st=document.getElementById('live-status');
const lam=document.getElementById('lam'),dt=document.getElementById('dt');
const live={redraws:0,job:0,status:'',seconds:null,serverSeconds:null,topology:'',undo};window.polyvecLive=live;
let undoStack=[],last=JSON.stringify(P.points);
function say(text,bad){st.textContent=text;st.style.color=bad?'#b00':'#070';live.status=text}
function params(){return {lam:+lam.value,dt:+dt.value}}
function links(){const q='lam='+lam.value+'&dt='+dt.value;
 history.replaceState(null,'','?'+q);  // a reload keeps the settings
 document.getElementById('dl-svg').href='/svg/'+REL+'?'+q;document.getElementById('dl-bezier').href='/svg/'+REL+'?bezier=1&'+q}
async function run(withEdits){const body=params();body.topology=live.topology;if(withEdits)body.edits=P.edits();const t0=performance.now();
 say('running…');let r,j;
 try{r=await fetch('/api/run/'+REL,{method:'POST',headers:{'content-type':'application/json'},body:JSON.stringify(body)});
  j=await r.json()}catch(e){say('the server does not answer ('+e+')',true);return}
 if(!r.ok){say(j.error||('error '+r.status),true);return}
 live.job=j.job;poll(j.job,t0)}
async function poll(id,t0){for(;;){let j;
 try{j=await (await fetch('/api/job/'+id+'?wait=30')).json()}catch(e){say('the server does not answer ('+e+')',true);return}
 if(id!==live.job)return;  // a newer edit or setting: its own poll redraws
 if(j.state==='done'){j.layers.forEach(L=>{const g=document.getElementById('layer-'+L.id);if(g)g.innerHTML=L.svg});
  live.topology=j.topology;live.serverSeconds=j.seconds;
  window.dispatchEvent(new Event('resize'));  // the page's own handler sizes the new end markers; the view box stays
  live.seconds=(performance.now()-t0)/1000;live.redraws++;say('redrawn ('+live.seconds.toFixed(2)+' s)');return}
 if(j.state==='failed'||j.state==='superseded'||j.error){say(j.error||j.state,true);return}
 }}  // ?wait=30: the server answers when the job ends
P.onEdit=()=>{undoStack.push(last);last=JSON.stringify(P.points);run(true)};
function undo(){if(!undoStack.length){say('nothing to undo');return}last=undoStack.pop();
 P.points.splice(0,P.points.length,...JSON.parse(last));P.draw();run(true)}
document.getElementById('undo').addEventListener('click',undo);
[lam,dt].forEach(s=>{s.addEventListener('input',()=>{document.getElementById(s.id+'-value').textContent=s.value});
 s.addEventListener('change',()=>{links();run(false)})});
const KEYS={e:1,j:3,c:5};
document.addEventListener('keydown',e=>{if(e.target.tagName==='INPUT'&&e.target.type!=='radio'||e.target.tagName==='TEXTAREA')return;
 if((e.ctrlKey||e.metaKey)&&e.key==='z'){e.preventDefault();undo();return}
 const t=KEYS[e.key];if(t&&!e.ctrlKey&&!e.metaKey&&!e.altKey){document.getElementById('add-t'+t).checked=true}});
})();
"""


def live_script(rel: str) -> str:
    """The script that makes the inspection page live for the drawing ``rel``."""
    return _LIVE_JS % {"rel": json.dumps(quote(rel)).replace("</", "<\\/")}
