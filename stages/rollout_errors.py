#!/usr/bin/env python3
"""Tracking errors of recorded rollouts against their reference frames, by step.

Usage: python3 stages/rollout_errors.py RUN_FOLDER EVAL_FOLDER [STEP ...]

RUN_FOLDER holds frames.parquet (from `skillaug ingest`); EVAL_FOLDER holds
eval_rollouts.parquet (from `skillaug eval ... --record N`). For each step
asked (default 1 5 10 20 30 40 60 80) it prints, averaged over the recorded
trials that have an unmasked reference at that step: the root's horizontal
and vertical distance to the reference root (m), the RMS joint exp-map error
by group (legs, trunk, arms, fingers; rad), the ball's distance from the
root against the reference's (m), the ball's distance to the reference ball
(m) and the SM reward. Reference positions are the clip's own (not moved by
a continuation's anchor), so use it on steps before the first seam or on
cells without continuation (`nr`). BallPlay only: the body groups are those
of its 53-body humanoid and the ball is object 0. Needs pyarrow and numpy
(what `.ci/run` installs), not pandas.
"""
import sys

import numpy as np
import pyarrow.parquet as pq

# body indices of the 53-body BallPlay humanoid (docs/simulation.md); joint j
# drives body j + 1
LEGS = range(1, 9)
TRUNK = range(9, 15)
ARMS = [15, 16, 17, 18, 34, 35, 36, 37]
FINGERS = list(range(19, 34)) + list(range(38, 53))


def rms(d, bodies):
    j = d.reshape(-1, 3)[[b - 1 for b in bodies]]
    return float(np.sqrt(np.mean(j ** 2)))


def main():
    run, ev = sys.argv[1], sys.argv[2]
    steps = [int(s) for s in sys.argv[3:]] or [1, 5, 10, 20, 30, 40, 60, 80]
    # pyarrow and numpy only (no pandas): columns as Python lists
    f = pq.read_table(
        f"{run}/frames.parquet", columns=["clip_id", "frame", "root_pos", "joint_rot", "obj_pos"]
    ).to_pydict()
    ref = {
        (c, k): (np.array(p), np.array(j), np.array(o))
        for c, k, p, j, o in zip(f["clip_id"], f["frame"], f["root_pos"], f["joint_rot"], f["obj_pos"])
    }
    cols = ["step", "ref_clip", "ref_frame", "root_pos", "joint_rot", "obj_pos", "sm_reward"]
    r = pq.read_table(f"{ev}/eval_rollouts.parquet", columns=cols).to_pydict()
    rows = {}
    for step, rc, rf, root, joints, obj, sm in zip(*(r[c] for c in cols)):
        if step not in steps or rc is None:
            continue
        p, j, o = ref[(int(rc), int(rf))]
        root = np.array(root)
        d = np.array(joints) - j
        ball = np.array(obj)[:3]
        rows.setdefault(step, []).append([
            np.linalg.norm(root[:2] - p[:2]), abs(root[2] - p[2]),
            rms(d, LEGS), rms(d, TRUNK), rms(d, ARMS), rms(d, FINGERS),
            np.linalg.norm(ball - root), np.linalg.norm(o[:3] - p),
            np.linalg.norm(ball - o[:3]), sm if sm is not None else np.nan,
        ])
    print("step trials root_xy root_z legs trunk arms fingers ball-root (ref) ball_err sm")
    for s in steps:
        if s in rows:
            m = np.nanmean(np.array(rows[s], dtype=float), axis=0)
            print(f"{s:4d} {len(rows[s]):6d} " + " ".join(f"{v:.3f}" for v in m))


if __name__ == "__main__":
    main()
