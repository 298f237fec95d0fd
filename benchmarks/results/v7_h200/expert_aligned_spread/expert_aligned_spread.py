"""The TCP where each motion of the insert_peg expert ends, in the frame of the box's face (x along the hole's
axis, into the box; mm and xyz Euler degrees), with the expert's success and the peg's half-length, one JSON line
per seed. Motions: pre-grasp, grasp, the first aligned pose, 3 refinements, the insertion (index 6).

    python benchmarks/results/v7_h200/expert_aligned_spread/expert_aligned_spread.py FIRST_SEED END_SEED > out.jsonl

Run on the 2-vCPU development machine, 2026-11-25, seeds 10000-10049 (two processes of 25 seeds): v6.jsonl with
the expert in rvt2, fixed_offsets.jsonl with ../expert_fixed_offsets.patch applied. stats.txt: `summary.py`.
"""
import sys, json, numpy as np
from scipy.spatial.transform import Rotation as R
import rvt2cli.record.experts as ex
from rvt2cli.tasks import get_task
from rvt2cli.record.scene import make_env
task = get_task('insert_peg'); env = make_env(task); u = env.unwrapped
orig = ex._solver; targets = []
def solver(env, speed):
    s = orig(env, speed); m = s.move_to_pose_with_screw
    def mv(pose, *a, **k):
        r = m(pose, *a, **k); tcp = u.agent.tcp.pose
        targets.append((tcp.p[0].cpu().numpy().copy(), tcp.q[0].cpu().numpy().copy())); return r
    s.move_to_pose_with_screw = mv; return s
ex._solver = solver
def T(p, q):
    M = np.eye(4); M[:3,:3] = R.from_quat([q[1],q[2],q[3],q[0]]).as_matrix(); M[:3,3] = p; return M
a, b = int(sys.argv[1]), int(sys.argv[2])
for seed in range(a, b):
    targets.clear(); ex.insert_peg(env, seed=seed)
    hole = u.box_hole_pose; H = T(hole.p[0].cpu().numpy(), hole.q[0].cpu().numpy()); hl = u.peg_half_sizes[0,0].item()
    face = H @ T([-hl,0,0],[1,0,0,0])
    rel = [(np.linalg.inv(face) @ T(p,q)) for p,q in targets]
    print(json.dumps(dict(seed=seed, ok=bool(u.evaluate()['success'][0]), hl=hl, n=len(targets),
        kf=[(np.round(r[:3,3]*1000,1).tolist(), np.round(R.from_matrix(r[:3,:3]).as_euler('xyz',degrees=True),1).tolist()) for r in rel])), flush=True)
