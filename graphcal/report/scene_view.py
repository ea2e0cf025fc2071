"""A :class:`~graphcal.report.scene_3d.Scene` drawn for a person: an interactive 3-D view inside a
report page (a ``<canvas>``, a small inline script and the scene as inline JSON: no network, no
library, a few kB of code), and a static matplotlib view of the same scene for printing.

The view: drag to turn, wheel to zoom, a checkbox per group. Coordinates go to the page in mm
as integers (world frame, relative to the scene's centre). When drawn, the canvas carries
``data-drawn`` (the number of points and segments drawn) for the tests.
"""

from __future__ import annotations

import json

import numpy as np

from graphcal.report.page import Markup, esc

__all__ = ["scene_html", "scene_figure", "floor_figure"]

_SCRIPT = """
(function(){
const el=document.getElementById(%(id)s), S=JSON.parse(el.querySelector('script').textContent);
const cv=el.querySelector('canvas'), ctx=cv.getContext('2d'), box=el.querySelector('.toggles');
let az=-0.9, el_=0.14, zoom=1.0, drag=null, k=1;
const sel=el.querySelector('select'); sel.onchange=()=>{k=Number(sel.value);fit();draw();};
S.groups.forEach((g,i)=>{const l=document.createElement('label');const c=document.createElement('input');
 c.type='checkbox';c.checked=g.visible;c.onchange=()=>{g.visible=c.checked;draw();};
 l.appendChild(c);const sw=document.createElement('span');sw.textContent=' \\u25A0 ';sw.style.color=g.color;
 l.appendChild(sw);l.appendChild(document.createTextNode(g.name+'  '));box.appendChild(l);});
let ox=0, oy=0;
function proj(){const ca=Math.cos(az),sa=Math.sin(az),ce=Math.cos(el_),se=Math.sin(el_);
 return (x,y,z)=>{const u=ca*x+sa*y, v=-sa*x+ca*y, zz=S.floor+(z-S.floor)*k; return [u, ce*zz-se*v];};}
function fit(){const Q=proj();let a=[1e18,1e18,-1e18,-1e18];
 for(const g of S.groups){if(!g.visible)continue;const d=g.data;for(let i=0;i<d.length;i+=3){const q=Q(d[i],d[i+1],d[i+2]);
  a=[Math.min(a[0],q[0]),Math.min(a[1],q[1]),Math.max(a[2],q[0]),Math.max(a[3],q[1])];}}
 if(a[0]>a[2]){zoom=1;ox=0;oy=0;return;}
 const f0=0.45*Math.min(cv.width,cv.height)/S.radius;
 zoom=0.9*Math.min(cv.width/Math.max(a[2]-a[0],1e-9),cv.height/Math.max(a[3]-a[1],1e-9))/f0;
 ox=-(a[0]+a[2])/2; oy=-(a[1]+a[3])/2;}
function draw(){
 const w=cv.width,h=cv.height,Q=proj(),f=zoom*0.45*Math.min(w,h)/S.radius;
 const P=(x,y,z)=>{const q=Q(x,y,z); return [w/2+f*(q[0]+ox), h/2-f*(q[1]+oy)];};
 ctx.fillStyle='#fff';ctx.fillRect(0,0,w,h);let n=0;
 for(const g of S.groups){ if(!g.visible) continue; const d=g.data;
  if(g.kind==='points'){ctx.fillStyle=g.color;
   const r=g.size;for(let i=0;i<d.length;i+=3){const p=P(d[i],d[i+1],d[i+2]);ctx.fillRect(p[0]-r/2,p[1]-r/2,r,r);n++;}}
  else{const cs=g.cycle.length?g.cycle:[g.color];ctx.lineWidth=1.5;
   for(let k=0;k<cs.length;k++){ctx.strokeStyle=cs[k];ctx.beginPath();
    for(let i=6*k;i<d.length;i+=6*cs.length){const a=P(d[i],d[i+1],d[i+2]),b=P(d[i+3],d[i+4],d[i+5]);
     ctx.moveTo(a[0],a[1]);ctx.lineTo(b[0],b[1]);n++;} ctx.stroke();}}}
 cv.dataset.drawn=n;}
cv.onmousedown=e=>{drag=[e.clientX,e.clientY];};
window.addEventListener('mouseup',()=>{drag=null;});
window.addEventListener('mousemove',e=>{if(!drag)return;az-=(e.clientX-drag[0])*0.01;
 el_=Math.max(-1.55,Math.min(1.55,el_+(e.clientY-drag[1])*0.01));drag=[e.clientX,e.clientY];draw();});
cv.onwheel=e=>{e.preventDefault();zoom*=Math.exp(-e.deltaY*0.001);draw();};
el.querySelector('button').onclick=()=>{az=-0.9;el_=0.14;fit();draw();};
fit();draw();})();
"""


def _payload(scene) -> tuple[dict, np.ndarray]:
    blocks = [g.data.reshape(-1, 3) for g in scene.groups if g.data.size]
    allp = np.vstack(blocks) if blocks else np.zeros((1, 3))
    center = 0.5 * (allp.min(axis=0) + allp.max(axis=0))
    radius = float(max(np.max(np.linalg.norm(allp - center, axis=1)), 1e-3)) * 1000.0
    groups = [{"name": g.name, "color": g.color, "kind": g.kind, "visible": bool(g.visible), "cycle": list(g.cycle),
               "size": float(g.size),
               "data": np.rint((g.data.reshape(-1, 3) - center) * 1000.0).astype(int).ravel().tolist()}
              for g in scene.groups]
    return {"radius": radius, "floor": float(-center[2] * 1000.0), "groups": groups}, center


def scene_html(scene, element_id: str = "scene3d", *, width: int = 960, height: int = 560) -> Markup:
    """The interactive view of ``scene`` as an HTML fragment (canvas, toggles, inline JSON and script)."""
    payload, _ = _payload(scene)
    data = json.dumps(payload, separators=(",", ":")).replace("</", "<\\/")
    script = _SCRIPT % {"id": json.dumps(element_id)}
    return Markup(
        f'<div id="{esc(element_id)}" class="scene3d">'
        f'<canvas width="{int(width)}" height="{int(height)}" style="border:1px solid #ccc;max-width:100%;'
        f'cursor:grab"></canvas><div class="small toggles"></div>'
        f'<p class="small">Drag to turn, wheel to zoom. <button type="button">reset view</button> Heights above '
        f'the floor: <select><option value="1">×1</option><option value="10">×10</option>'
        f'<option value="50">×50</option></select></p>'
        f'<script type="application/json">{data}</script><script>{script}</script></div>'
    )


def scene_figure(scene, *, elev: float = 8.0, azim: float = -52.0):
    """The same scene as a matplotlib Figure (3-D axes, equal scale), for printing."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    from graphcal.report.plots import new_figure

    fig = new_figure(8.0, 5.6)
    ax = fig.add_subplot(1, 1, 1, projection="3d")
    for g in scene.groups:
        if not g.visible or not g.data.size:
            continue
        if g.kind == "points":
            p = g.data
            ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=0.3 * g.size**2, c=g.color, depthshade=False, label=g.name)
        else:
            cycle = g.cycle or (g.color,)
            colors = [cycle[i % len(cycle)] for i in range(len(g.data))]
            ax.add_collection3d(Line3DCollection(g.data, colors=colors, linewidths=0.9))
    blocks = [g.data.reshape(-1, 3) for g in scene.groups if g.data.size]
    if blocks:
        allp = np.vstack(blocks)
        c, r = 0.5 * (allp.min(axis=0) + allp.max(axis=0)), 0.5 * float(np.ptp(allp, axis=0).max())
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[1] - r, c[1] + r)
        ax.set_zlim(c[2] - r, c[2] + r)
        ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x world [m]")
    ax.set_ylabel("y world [m]")
    ax.set_zlabel("z world [m]")
    if any(g.kind == "points" for g in scene.groups):
        ax.legend(loc="upper left", fontsize=7, markerscale=8)
    return fig


def floor_figure(scene):
    """Per sensor, the height above the floor (mm) of its ground points against their world x (m),
    with the prior extrinsic and with the calibrated one: the spread, then the collapse."""
    from graphcal.report.plots import new_figure

    n = max(len(scene.ground), 1)
    fig = new_figure(8.0, 2.6 * n)
    for i, (name, (pri, cal)) in enumerate(scene.ground.items()):
        ax = fig.add_subplot(n, 1, i + 1)
        for pts, color, label in ((pri, "#ff7f0e", "prior (CAD) extrinsic"), (cal, "#1f77b4", "calibrated")):
            rms = float(np.sqrt(np.mean(pts[:, 2] ** 2))) * 1e3
            ax.scatter(pts[:, 0], pts[:, 2] * 1e3, s=0.8, c=color, label=f"{label}: RMS {rms:.2f} mm")
        ax.axhline(0.0, color="#555", lw=0.8)
        ax.set_xlabel("x world [m]")
        ax.set_ylabel("height above floor [mm]")
        ax.set_title(f"{name}: ground points of every station, world frame", fontsize=9)
        ax.legend(loc="upper right", fontsize=7, markerscale=8)
    return fig
