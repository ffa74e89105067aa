"""Issue 16: line sources on both sides of a 1 m focus (system 2, 1024² crop, renderer centres).

Run:  python benchmarks/diagnose_lines.py 380,560,720,1500,2200,2900 1024
(~1 min per case: the line fit of a 500-800 lenslet region).
"""
# ruff: noqa
import sys, time, numpy as np
sys.path.insert(0, "/work/wt-i16")
from lfcam.camera import load_profile
from lfcam.distance import run_distance
from lfcam.measure import Geometry
from lfcam.measure.lenslets import build_lenslet_map
from lfcam.measure.pointfit import chief_ray_offset
from lfcam.sim.capture import apply_overrides, simulate
from lfcam.sim.render import Renderer
from lfcam.sim.scene import scene_from_dict
import lfcam.measure.lightfield as LF
SIZE=int(sys.argv[2]) if len(sys.argv)>2 else 768
CAM={"mla":{"focus_mm":1000.0,"rotation_rad":0.012},"sensor":{"width_px":SIZE,"height_px":SIZE}}
def geom(profile):
    rend=Renderer(profile); lens_mm=np.stack([rend.lcx,rend.lcy],1)
    mag=1+profile.mla.focal_length_mm/(profile.d_in_mm-profile.main_lens.exit_pupil_z_mm)
    pitch_px=profile.mla.pitch_mm/profile.sensor.pixel_pitch_mm*mag
    lmap=build_lenslet_map(rend.predicted_centres_px(),(SIZE,SIZE),0.54*pitch_px)
    return Geometry(lmap,lens_mm,pitch_px,profile.d_in_mm)
base=load_profile("system2"); prof=apply_overrides(base,CAM)
G=geom(prof)
dists=[float(x) for x in sys.argv[1].split(",")]
for d in dists:
  for ang in (0, 60, 135):
    t=np.radians(ang); u=np.array([np.cos(t),np.sin(t)])
    a=chief_ray_offset(prof,prof.d_in_mm,d,-1.5*u); b=chief_ray_offset(prof,prof.d_in_mm,d,1.5*u)
    sc={"seed":3,"camera":CAM,"sensor":{"photon_noise":True,"full_well_e":20000,"read_noise_e":3.0},
        "objects":[{"type":"line","distance_mm":d,"start_mm":list(map(float,a)),"end_mm":list(map(float,b)),"rays":600000}]}
    t0=time.time(); raw,used,truth=simulate(base,scene_from_dict(sc)); t1=time.time()
    run=run_distance(raw.astype(np.float64),used,None,model="exact",geometry=G)
    for r in run.regions:
        print(f"{d:6.0f} {ang:4d} kind={r.kind:5s} st={r.status:10s} err={100*(r.distance_mm/d-1):+7.2f}% "
              f"render {t1-t0:.1f}s fit {time.time()-t1:.1f}s", flush=True)
