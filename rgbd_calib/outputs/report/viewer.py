"""The inline 3D viewer of the report page: its data (cameras, board poses and the cloud in
display coordinates, compact base64) and its script, a small canvas renderer (no WebGL, no
network, no external script).
"""

from __future__ import annotations

import base64
import json
from typing import Any

import numpy as np

from .cloud import Cloud
from .figures import palette
from .layout import board_outline, frustum, rig_size

VIEWER_JS = r"""
(function(){
var D=JSON.parse(document.getElementById('viewer-data').textContent);
var cv=document.getElementById('viewer'),ctx=cv.getContext('2d');
function dec(s,T){var b=atob(s),u=new Uint8Array(b.length);for(var i=0;i<b.length;i++)
u[i]=b.charCodeAt(i);return new T(u.buffer);}
var n=D.cloud?D.cloud.n:0,P=new Float32Array(3*n),C=n?dec(D.cloud.cam,Uint8Array):null,
RGB=(n&&D.cloud.rgb)?dec(D.cloud.rgb,Uint8Array):null;
if(n){var q=dec(D.cloud.xyz,Int16Array);for(var i=0;i<3*n;i++)P[i]=q[i]*D.cloud.scale+
D.cloud.offset[i%3];}
var st={yaw:-0.6,pitch:0.5,dist:D.dist,rgb:false,boards:true};
function home(){st.yaw=-0.6;st.pitch=0.5;st.dist=D.dist;}
function project(W,H){var cy=Math.cos(st.yaw),sy=Math.sin(st.yaw),cp=Math.cos(st.pitch),
sp=Math.sin(st.pitch),f=0.9*Math.min(W,H),t=D.target;return function(x,y,z){x-=t[0];y-=t[1];
z-=t[2];var x1=cy*x-sy*y,y1=sy*x+cy*y,y2=cp*y1-sp*z,z2=sp*y1+cp*z,d=st.dist+y2;
if(d<0.05)return null;return [W/2+f*x1/d,H/2-f*z2/d,d];};}
function draw(){var r=window.devicePixelRatio||1,W=Math.max(cv.clientWidth,300)*r,
H=Math.max(cv.clientHeight,200)*r;cv.width=W;cv.height=H;var pr=project(W,H);
var img=ctx.createImageData(W,H),px=img.data,zb=new Float32Array(W*H).fill(1e9),s=Math.max(
2,Math.round(2*r)),drawn=0;for(var k=3;k<px.length;k+=4){px[k-3]=17;px[k-2]=21;px[k-1]=28;
px[k]=255;}for(var i=0;i<n;i++){var p=pr(P[3*i],P[3*i+1],P[3*i+2]);if(!p)continue;var u=p[0]|0,
v=p[1]|0;if(u<0||v<0||u>=W-s||v>=H-s)continue;var c=st.rgb&&RGB?[RGB[3*i],RGB[3*i+1],
RGB[3*i+2]]:D.colors[C[i]];drawn++;for(var a=0;a<s;a++)for(var b=0;b<s;b++){var o=(v+b)*W+u+a;
if(p[2]<zb[o]){zb[o]=p[2];px[4*o]=c[0];px[4*o+1]=c[1];px[4*o+2]=c[2];}}}
ctx.putImageData(img,0,0);function line(a,b,col,w){var p=pr(a[0],a[1],a[2]),
q=pr(b[0],b[1],b[2]);if(!p||!q)return;ctx.strokeStyle=col;ctx.lineWidth=w*r;ctx.beginPath();
ctx.moveTo(p[0],p[1]);ctx.lineTo(q[0],q[1]);ctx.stroke();}
if(st.boards)D.boards.forEach(function(b){for(var j=0;j<4;j++)line(b[j],b[(j+1)%4],
'rgba(200,200,200,0.55)',1);});
D.cameras.forEach(function(c){var col='rgb('+c.color.join(',')+')',f=c.frustum,w=c.ref?2.5:1.5;
for(var j=1;j<5;j++){line(f[0],f[j],col,w);line(f[j],f[j%4+1],col,w);}var p=pr(f[0][0],f[0][1],
f[0][2]);if(p){ctx.fillStyle=col;ctx.font=(12*r)+'px sans-serif';ctx.fillText(c.name+(c.ref?
' (ref)':''),p[0]+4*r,p[1]-4*r);}});
cv.dataset.pointsDrawn=drawn;cv.dataset.frames=(+cv.dataset.frames||0)+1;}
var drag=null;cv.addEventListener('mousedown',function(e){drag=[e.clientX,e.clientY];});
window.addEventListener('mouseup',function(){drag=null;});
window.addEventListener('mousemove',function(e){if(!drag)return;st.yaw+=(e.clientX-drag[0])*
0.008;st.pitch=Math.max(-1.57,Math.min(1.57,st.pitch+(e.clientY-drag[1])*0.008));
drag=[e.clientX,e.clientY];draw();});
cv.addEventListener('wheel',function(e){e.preventDefault();st.dist*=Math.exp(e.deltaY*0.001);
draw();},{passive:false});
function btn(id,fn){document.getElementById(id).addEventListener('click',function(){fn();draw();
});}
btn('v-top',function(){st.pitch=1.5707;st.yaw=0;});btn('v-side',function(){st.pitch=0;
st.yaw=0;});btn('v-home',home);btn('v-color',function(){st.rgb=!st.rgb;});
btn('v-boards',function(){st.boards=!st.boards;});
window.addEventListener('resize',draw);draw();cv.dataset.ready='yes';
})();
"""


def viewer_data(report: dict[str, Any], cloud: Cloud | None, frame: np.ndarray) -> str:
    """JSON for the inline 3D viewer, in display coordinates (e1, e2, up); the cloud as
    base64 int16 steps of `scale` metres (>= 1 mm) around its centre, camera index and RGB
    as base64 bytes."""
    colors = [[int(round(255 * c)) for c in col] for col in palette(report)]
    size = rig_size(report)
    cams = []
    for i, (name, cam) in enumerate(report["cameras"].items()):
        if cam["T_ref_cam"] is None:
            continue
        ref = name == report["reference"]
        cams.append(
            {
                "name": name,
                "ref": ref,
                "color": colors[i],
                "frustum": np.round(frustum(cam, 0.12 * size) @ frame.T, 4).tolist(),
            }
        )
    boards = [
        np.round(board_outline(report, np.asarray(b["T_ref_board"], float)) @ frame.T, 4).tolist()
        for b in report["board_views"]
    ]
    # look at the middle of cameras and board poses, from far enough to see all of them
    centres = np.array([c["frustum"][0] for c in cams])
    origins = (
        np.array(
            [np.asarray(b["T_ref_board"], float)[:3, 3] for b in report["board_views"]]
        ).reshape(-1, 3)
        @ frame.T
    )
    target = (centres.mean(0) + origins.mean(0)) / 2 if len(origins) else centres.mean(0)
    radius = float(np.linalg.norm(np.vstack([centres, origins]) - target, axis=1).max())
    data: dict[str, Any] = {
        "cameras": cams,
        "boards": boards,
        "colors": colors,
        "target": np.round(target, 4).tolist(),
        "dist": round(3.0 * max(radius, 0.2 * size) + 0.5, 3),
        "cloud": None,
    }
    if cloud is not None and len(cloud.points):
        p = cloud.points @ frame.T
        offset = np.round((p.max(0) + p.min(0)) / 2, 3)
        scale = max(float(np.abs(p - offset).max()) / 32000.0, 0.001)
        q = np.clip(np.round((p - offset) / scale), -32767, 32767).astype("<i2")
        data["cloud"] = {
            "n": int(len(p)),
            "scale": scale,
            "offset": offset.tolist(),
            "xyz": base64.b64encode(q.tobytes()).decode("ascii"),
            "cam": base64.b64encode(cloud.camera.astype(np.uint8).tobytes()).decode("ascii"),
            "rgb": None
            if cloud.rgb is None
            else base64.b64encode(np.ascontiguousarray(cloud.rgb, np.uint8).tobytes()).decode(),
        }
    return json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
