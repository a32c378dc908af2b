"""An interactive viewer of a run: one self-contained HTML page (no server, no network).

The page draws the focal plane on a canvas: every positioner's two arms and fiber, coloured by
its outcome, its target; a time slider with play and pause; hover or click shows the id, the
outcome and why; a search box finds a positioner by id; pairs the verifier found colliding and
positioners with limit violations are drawn in red and listed; a clicked positioner's joint
angles are plotted against time.

Size: the joint angles are stored as base-64 16-bit integers (resolution ``2 pi / 65536`` rad,
~2.4 um at a 25 mm reach) on at most ``MAX_FRAMES`` frames, and fewer for large runs so that
frames x positioners stays within ``MAX_SAMPLES`` (DESI 5000: 160 frames, ~3 MB); the frames are
evenly spaced in time and always include the first and the last sample. Drawing a frame is one
pass over the positioners (two line segments each), which keeps 5000 positioners fluid.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

import numpy as np

from fiberplan._atomic import atomic_path
from fiberplan._json import json_ready
from fiberplan.kinematics import fiber_positions
from fiberplan.outcomes import explain
from fiberplan.trajectory import PlanResult
from fiberplan.verify import VerificationReport

MAX_FRAMES = 400
MAX_SAMPLES = 800_000  # frames x positioners
_SCALE = 32768 / np.pi  # radians -> int16 (angles wrapped into [-pi, pi))


def frame_indices(n_samples: int, n_positioners: int) -> np.ndarray:
    """Sample indices of the frames: evenly spaced, first and last included."""
    frames = int(min(MAX_FRAMES, max(2, MAX_SAMPLES // max(1, n_positioners)), n_samples))
    return np.unique(np.round(np.linspace(0, n_samples - 1, max(frames, 1))).astype(int))


def _pack(angles: np.ndarray, centre: float) -> str:
    """Angles as base-64 little-endian int16 of ``angle - centre`` (within pi of the centre of
    the joint's hard stops, so no angle wraps)."""
    wrapped = (angles - centre + np.pi) % (2 * np.pi) - np.pi
    return base64.b64encode(np.round(wrapped * _SCALE).clip(-32768, 32767).astype("<i2").tobytes()).decode("ascii")


def page_data(result: PlanResult, report: VerificationReport | None) -> dict[str, Any]:
    """What the page draws, JSON-ready."""
    scenario, traj = result.scenario, result.trajectory
    inst = scenario.instrument
    frames = frame_indices(len(traj.times), scenario.n_positioners)
    joints = traj.joints[frames]  # (F, N, 2)
    outcome = np.asarray(result.outcome)
    reasons = explain(scenario, traj.joints[-1], outcome)
    colliding: dict[int, list[str]] = {}
    limits: dict[int, list[str]] = {}
    if report is not None:
        for c in report.collisions:
            colliding.setdefault(c.id_i, []).append(f"collides with {c.id_j} from t = {c.t_first_s:.2f} s ({c.overlap_mm:.3f} mm)")
            colliding.setdefault(c.id_j, []).append(f"collides with {c.id_i} from t = {c.t_first_s:.2f} s ({c.overlap_mm:.3f} mm)")
        for v in report.limit_violations:
            limits.setdefault(v.positioner_id, []).append(f"{v.joint} {v.kind} at t = {v.t_s:.2f} s")
    target_xy = np.where(scenario.has_target[:, None], scenario.target_xy, np.nan)
    return json_ready({
        "title": f"{result.planner} | {inst.name} | {scenario.name or scenario.kind} | {scenario.n_positioners} positioners",
        "ids": scenario.ids.tolist(),
        "base": np.round(scenario.base_xy, 4).tolist(),
        "orient": np.round(scenario.orient, 6).tolist(),
        "arms": [inst.alpha_arm_mm, inst.beta_arm_mm],
        "times": np.round(traj.times[frames], 4).tolist(),
        "all_times": bool(len(frames) == len(traj.times)),
        "n_frames": len(frames),
        "alpha": _pack(joints[:, :, 0], float(np.mean(inst.alpha_limits_rad))),
        "beta": _pack(joints[:, :, 1], float(np.mean(inst.beta_limits_rad))),
        "centre": [float(np.mean(inst.alpha_limits_rad)), float(np.mean(inst.beta_limits_rad))],
        "target": [[None, None] if not np.isfinite(p).all() else [round(float(p[0]), 4), round(float(p[1]), 4)] for p in target_xy],
        "outcome": outcome.tolist(),
        "reason": {str(k): v for k, v in reasons.items()},
        "colliding": {str(k): v for k, v in colliding.items()},
        "limits": {str(k): v for k, v in limits.items()},
        "verified": None if report is None else bool(report.ok),
        "final_xy": np.round(fiber_positions(inst, scenario.base_xy, scenario.orient, traj.joints[-1]), 4).tolist(),
    })


def write_viewer(result: PlanResult, report: VerificationReport | None, out: str | Path) -> Path:
    """Write the viewer page of ``result`` (with the verifier's ``report``) to ``out``, atomically."""
    data = json.dumps(page_data(result, report), separators=(",", ":"))
    html = _TEMPLATE.replace("/*DATA*/null", data)
    out = Path(out)
    with atomic_path(out, what="--out") as tmp:
        tmp.write_text(html)
    return out


_TEMPLATE = r"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>fiberplan viewer</title>
<style>
body{margin:0;font:13px system-ui,sans-serif;display:flex;height:100vh;color:#222}
#main{flex:1;display:flex;flex-direction:column;min-width:0}
#bar{display:flex;gap:8px;align-items:center;padding:6px;border-bottom:1px solid #ddd;flex-wrap:wrap}
#plane{flex:1;min-height:0;cursor:crosshair}
#side{width:330px;border-left:1px solid #ddd;padding:8px;overflow:auto}
#slider{flex:1;min-width:200px}
.key span{display:inline-block;width:10px;height:10px;margin:0 4px 0 10px;border-radius:2px}
#info{white-space:pre-wrap}
</style></head><body>
<div id="main">
 <div id="bar">
  <button id="play">play</button>
  <input id="slider" type="range" min="0" value="0" step="1">
  <span id="time"></span>
  <input id="search" placeholder="positioner id" size="10"><button id="find">find</button>
 </div>
 <canvas id="plane"></canvas>
</div>
<div id="side">
 <div id="title"></div>
 <div class="key" id="key"></div>
 <h4>Positioner</h4><div id="info">hover or click a positioner</div>
 <canvas id="profile" width="310" height="200"></canvas>
 <h4>Collisions and limit violations</h4><div id="problems"></div>
</div>
<script>
"use strict";
const D = /*DATA*/null;
const COLOURS = {reached:"#4a7fb5", held:"#8fa8c0", deadlocked:"#ff7f0e", unfinished:"#9467bd", failed:"#8c564b",
  infeasible:"#7f7f7f", locked:"#17becf", displaced:"#e377c2"};
const N = D.ids.length, F = D.n_frames;
function unpack(text,centre){const bytes=Uint8Array.from(atob(text),c=>c.charCodeAt(0));
  const ints=new Int16Array(bytes.buffer);const out=new Float32Array(ints.length);
  for(let k=0;k<ints.length;k++)out[k]=centre+ints[k]*Math.PI/32768;return out;}
const ALPHA = unpack(D.alpha,D.centre[0]), BETA = unpack(D.beta,D.centre[1]);
const index = new Map(D.ids.map((id,k)=>[id,k]));
const canvas = document.getElementById("plane"), ctx = canvas.getContext("2d");
const slider = document.getElementById("slider");
slider.max = F - 1;
let frame = 0, playing = false, selected = -1, hover = -1, view = null;
const viewer = window.viewer = {get frame(){return frame;}, set frame(f){setFrame(f);}, drawn: 0, selected: ()=>selected};
document.getElementById("title").textContent = D.title + (D.verified===null ? "" : (D.verified ? " | verified" : " | NOT verified"));
document.getElementById("key").innerHTML = Object.keys(COLOURS).filter(o=>D.outcome.includes(o))
  .map(o=>`<span style="background:${COLOURS[o]}"></span>${o} (${D.outcome.filter(x=>x===o).length})`).join("")
  + (Object.keys(D.colliding).length||Object.keys(D.limits).length ? '<span style="background:#d62728"></span>collision / limit' : "");
function bounds(){let x0=Infinity,x1=-Infinity,y0=Infinity,y1=-Infinity;const r=D.arms[0]+D.arms[1];
  for(const [x,y] of D.base){x0=Math.min(x0,x-r);x1=Math.max(x1,x+r);y0=Math.min(y0,y-r);y1=Math.max(y1,y+r);}return [x0,x1,y0,y1];}
const B = bounds();
function resize(){const r=canvas.getBoundingClientRect();canvas.width=Math.max(100,r.width)*devicePixelRatio;canvas.height=Math.max(100,r.height)*devicePixelRatio;
  const s=Math.min(canvas.width/(B[1]-B[0]),canvas.height/(B[3]-B[2]));
  view={s, ox:(canvas.width-s*(B[1]-B[0]))/2-s*B[0], oy:(canvas.height+s*(B[3]-B[2]))/2+s*B[2]};draw();}
function px(x,y){return [view.ox+view.s*x, view.oy-view.s*y];}
function arms(k,f){const a=ALPHA[f*N+k]+D.orient[k], b=a+BETA[f*N+k];const [bx,by]=D.base[k];
  const ex=bx+D.arms[0]*Math.cos(a), ey=by+D.arms[0]*Math.sin(a);return [bx,by,ex,ey,ex+D.arms[1]*Math.cos(b),ey+D.arms[1]*Math.sin(b)];}
function problem(k){const id=String(D.ids[k]);return id in D.colliding || id in D.limits;}
function draw(){if(!view)return;ctx.clearRect(0,0,canvas.width,canvas.height);
  ctx.lineCap="round";const w=Math.max(1,view.s*0.6);
  ctx.fillStyle="#bbb";for(let k=0;k<N;k++){const t=D.target[k];if(t[0]===null)continue;const [x,y]=px(t[0],t[1]);ctx.fillRect(x-1.5,y-1.5,3,3);}
  const groups={};for(let k=0;k<N;k++){const c=problem(k)?"#d62728":COLOURS[D.outcome[k]]||"#444";(groups[c]=groups[c]||[]).push(k);}
  for(const c in groups){ctx.strokeStyle=c;ctx.lineWidth=w;ctx.beginPath();
    for(const k of groups[c]){const p=arms(k,frame);const a=px(p[0],p[1]),b=px(p[2],p[3]),e=px(p[4],p[5]);ctx.moveTo(a[0],a[1]);ctx.lineTo(b[0],b[1]);ctx.lineTo(e[0],e[1]);}
    ctx.stroke();}
  for(const k of [hover,selected]){if(k<0)continue;const p=arms(k,frame);const e=px(p[4],p[5]);
    ctx.strokeStyle="#000";ctx.lineWidth=2;ctx.beginPath();ctx.arc(e[0],e[1],Math.max(6,view.s*2),0,2*Math.PI);ctx.stroke();}
  document.getElementById("time").textContent=`t = ${D.times[frame].toFixed(2)} s (frame ${frame+1} of ${F}${D.all_times?"":", decimated"})`;
  viewer.drawn++;}
function setFrame(f){frame=Math.max(0,Math.min(F-1,Math.round(f)));slider.value=frame;draw();}
slider.addEventListener("input",()=>setFrame(+slider.value));
document.getElementById("play").addEventListener("click",e=>{playing=!playing;e.target.textContent=playing?"pause":"play";
  if(playing&&frame>=F-1)setFrame(0);});
let last=0;function tick(t){if(playing&&t-last>40){last=t;if(frame>=F-1){playing=false;document.getElementById("play").textContent="play";}else setFrame(frame+1);}
  requestAnimationFrame(tick);}requestAnimationFrame(tick);
function nearest(ev){const r=canvas.getBoundingClientRect();const x=(ev.clientX-r.left)*devicePixelRatio,y=(ev.clientY-r.top)*devicePixelRatio;
  let best=-1,bd=Infinity;for(let k=0;k<N;k++){const p=arms(k,frame);const e=px(p[4],p[5]);const b=px(p[0],p[1]);
    const d=Math.min((e[0]-x)**2+(e[1]-y)**2,(b[0]-x)**2+(b[1]-y)**2);if(d<bd){bd=d;best=k;}}
  return bd<(view.s*(D.arms[0]+D.arms[1]))**2?best:-1;}
function describe(k){const id=String(D.ids[k]);let s=`id ${id}\noutcome: ${D.outcome[k]}`;
  if(id in D.reason)s+=`\nwhy: ${D.reason[id]}`;for(const m of (D.colliding[id]||[]).concat(D.limits[id]||[]))s+=`\n${m}`;
  const f=D.final_xy[k];s+=`\nfinal fiber: (${f[0].toFixed(3)}, ${f[1].toFixed(3)}) mm`;
  if(D.target[k][0]!==null)s+=`\ntarget: (${D.target[k][0].toFixed(3)}, ${D.target[k][1].toFixed(3)}) mm`;return s;}
canvas.addEventListener("mousemove",ev=>{const k=nearest(ev);if(k!==hover){hover=k;if(selected<0)document.getElementById("info").textContent=k<0?"":describe(k);draw();}});
canvas.addEventListener("click",ev=>select(nearest(ev)));
function select(k){selected=k;document.getElementById("info").textContent=k<0?"hover or click a positioner":describe(k);plotProfile(k);draw();}
function plotProfile(k){const c=document.getElementById("profile"),g=c.getContext("2d");g.clearRect(0,0,c.width,c.height);if(k<0)return;
  const t0=D.times[0],t1=D.times[F-1]||1;let lo=Infinity,hi=-Infinity;
  for(let f=0;f<F;f++){for(const v of [ALPHA[f*N+k],BETA[f*N+k]]){lo=Math.min(lo,v);hi=Math.max(hi,v);}}if(hi-lo<1e-6){hi+=0.1;lo-=0.1;}
  const X=t=>30+(c.width-40)*(t-t0)/Math.max(1e-9,t1-t0),Y=v=>c.height-20-(c.height-30)*(v-lo)/(hi-lo);
  g.strokeStyle="#999";g.strokeRect(30,10,c.width-40,c.height-30);g.fillStyle="#444";
  g.fillText(`${(hi*180/Math.PI).toFixed(0)} deg`,0,14);g.fillText(`${(lo*180/Math.PI).toFixed(0)}`,0,c.height-20);g.fillText(`${t1.toFixed(1)} s`,c.width-40,c.height-4);
  for(const [arr,col,name] of [[ALPHA,"#1f77b4","alpha"],[BETA,"#ff7f0e","beta"]]){g.strokeStyle=col;g.beginPath();
    for(let f=0;f<F;f++){const x=X(D.times[f]),y=Y(arr[f*N+k]);f?g.lineTo(x,y):g.moveTo(x,y);}g.stroke();}
  g.fillStyle="#1f77b4";g.fillText("alpha",40,22);g.fillStyle="#ff7f0e";g.fillText("beta",80,22);}
document.getElementById("find").addEventListener("click",()=>{const id=parseInt(document.getElementById("search").value,10);
  if(index.has(id))select(index.get(id));else document.getElementById("info").textContent=`no positioner ${document.getElementById("search").value}`;});
document.getElementById("search").addEventListener("keydown",e=>{if(e.key==="Enter")document.getElementById("find").click();});
const probs=Object.entries(D.colliding).concat(Object.entries(D.limits));
document.getElementById("problems").textContent=probs.length?probs.map(([id,m])=>`${id}: ${m.join("; ")}`).join("\n"):(D.verified===null?"not verified":"none");
window.addEventListener("resize",resize);resize();
</script></body></html>
"""
