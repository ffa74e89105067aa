"""Issue 16: d_in from 3x3 dots behind/in front of a 1 m focus, started 0 / +0.4 / -0.4 mm off.

Run:  python benchmarks/diagnose_din.py 1500,600 1280 6.5
"""
# ruff: noqa
import sys, time, numpy as np
sys.path.insert(0, "/work/wt-i16")
from lfcam.camera import load_profile
from lfcam.calibrate.reference import measure_d_in
from lfcam.measure.pointfit import chief_ray_offset
from lfcam.sim.capture import simulate, apply_overrides
from lfcam.sim.scene import scene_from_dict
SIZE=int(sys.argv[2]); sens=float(sys.argv[3])
cam={"sensor":{"width_px":SIZE,"height_px":SIZE},"mla":{"focus_mm":1000.0}}
base=load_profile("system2"); prof=apply_overrides(base,cam)
white,_,truth=simulate(base,scene_from_dict({"seed":1,"objects":[{"type":"white"}],"camera":cam,"rays_per_source":200000}))
L=truth["lenses"]; comp=np.array(L["complete"],bool); centres=np.array(L["centroid_px"])[comp]
for D in [float(x) for x in sys.argv[1].split(",")]:
    mag=1+prof.mla.focal_length_mm/(prof.d_in_mm-prof.main_lens.exit_pupil_z_mm)
    sp=abs(chief_ray_offset(prof,prof.d_in_mm,D,np.array([sens/mag,0.0]))[0])
    dots=[{"type":"point","distance_mm":D,"position_mm":[i*sp,j*sp]} for i in (-1,0,1) for j in (-1,0,1)]
    raw,used,_=simulate(base,scene_from_dict({"seed":2,"objects":dots,"camera":cam,"rays_per_source":200000,
       "sensor":{"photon_noise":True,"full_well_e":20000,"read_noise_e":3.0}}))
    for off in (0.0,0.4,-0.4):
        start=used.with_d_in(used.d_in_mm+off); t0=time.time()
        try:
            r=measure_d_in(raw.astype(np.float64),centres,start,D)
            print(f"{D:.0f} start {off:+.1f}: d_in {r.d_in_mm:.4f} err {100*(r.d_in_mm/used.d_in_mm-1):+.4f}% dots {len(r.exact)} rms max {max(f.rms_px for f in r.exact):.3f} {time.time()-t0:.0f}s",flush=True)
        except Exception as e:
            print(D,off,"ERR",e, f"{time.time()-t0:.0f}s",flush=True)
