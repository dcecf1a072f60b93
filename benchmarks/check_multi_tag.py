"""Two tags in one filter vs one tag: lever-arm errors and yaw convergence over noise seeds.

    python benchmarks/check_multi_tag.py [--seeds 8]

The ``excited-90s`` flight carrying the ``two-tags`` scenario's tags (front, back); per seed: time until
the world-yaw sd falls below 1 deg (two tags / front only), final yaw sd [deg], and the largest
lever-arm error per tag [cm].  Numbers in docs/estimator.md ("Several tags in one filter").
"""
import argparse
import numpy as np
from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.models import state as S
from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.sim import builtin_scenario, simulate
ex = builtin_scenario("excited-90s"); tags = builtin_scenario("two-tags").tags
def yaw_sd(res):
    return np.array([np.sqrt((quat_to_rotmat(x[S.Q]) @ C[S.ETH,S.ETH] @ quat_to_rotmat(x[S.Q]).T)[2,2]) for x,C in zip(res.states,res.covariances)])
rows=[]
ap = argparse.ArgumentParser(); ap.add_argument("--seeds", type=int, default=8); a = ap.parse_args()
print("seed t_yaw<1deg(two) t_yaw<1deg(one) yaw_sd_end(two) yaw_sd_end(one) max|err| front back [cm]")
for seed in range(1, a.seeds + 1):
    ds = simulate(ex.model_copy(update={"tags": tags, "seeds": ex.seeds.model_copy(update={"noise": seed})}))
    b = run_eskf(ds, EskfOptions()); o = run_eskf(ds, EskfOptions(tag="front"))
    yb, yo = yaw_sd(b), yaw_sd(o)
    e = {k: (np.array(v["lever_arm"]) - np.array(ds.meta.truth.tags[k]))*100 for k,v in b.calibration["tags"].items()}
    rows.append((seed, b.t[np.argmax(yb<np.radians(1))], o.t[np.argmax(yo<np.radians(1))], np.degrees(yb[-1]), np.degrees(yo[-1]), np.abs(e["front"]).max(), np.abs(e["back"]).max()))
    print(seed, *[round(float(v),2) for v in rows[-1][1:]])
r=np.array(rows); print("mean", r[:,1:].mean(0).round(2), "max lever err", r[:,5:].max(0).round(2))
