#!/usr/bin/env python3
"""Where the simulated ball is when the reference's hand meets it again.

Usage: python3 stages/catch_gap.py RUN_FOLDER EVAL_FOLDER

RUN_FOLDER is the `skillaug ingest` output the policy was trained on
(clips.parquet, frames.parquet; body order of `mocap_humanoid.xml`),
EVAL_FOLDER a `skillaug eval --record N` output (eval_rollouts.parquet).

A **catch** is a step of an SR trial whose reference frame is the first,
after the reference's ball has bounced (its vertical velocity turns
positive below 0.4 m), at which a hand body of the clip (wrist or finger
origin) is within 0.15 m of the clip's ball centre: the frame where the
clip's hand meets its rising ball again, as `catch_frame` in
src/sim/push.rs finds it. At each catch the script compares the
simulated ball's height with the reference ball's (the reference is
anchored by a rotation about the vertical and a horizontal shift, so
heights compare directly) and prints, per catch of a trial (first,
second, ...), the mean height gap over the trials that reach it, the
share of trials whose ball is within 0.15 m of the reference ball's
height (where the clip's hand meets it), and the share whose ball is
still at rest on the floor (below 0.13 m, moving slower than 0.2 m/s).
With `-v` it prints every trial's catches. Needs pyarrow only.
"""
import math
import os
import sys

import pyarrow.parquet as pq

# Wrist and finger bodies of both hands (mocap_humanoid.xml order,
# src/motion/layout.rs): left 18..=33, right 37..=52.
HAND_BODIES = list(range(18, 34)) + list(range(37, 53))
NEAR = 0.15  # m, hand body origin to ball centre (push.rs `hand_radius`)
BOUNCE_BELOW = 0.4  # m, a ball turning upwards below this has bounced
REACHABLE = 0.15  # m, height gap counted as "where the clip's hand meets it"


def load(run, ev, extra=()):
    """The clips' ids and rates, the reference per (clip id, frame): (ball
    height, ball vertical velocity, a clip hand within NEAR of the ball,
    ball position, root position, root rotation x, y, z, w), and the
    recorded SR trials: trial -> steps in order, each (step, ball
    position, clip index, frame) plus the columns named in `extra`."""
    for f in [f"{run}/clips.parquet", f"{run}/frames.parquet", f"{ev}/eval_rollouts.parquet"]:
        if not os.path.isfile(f):
            sys.exit(f"{os.path.basename(sys.argv[0])}: {f} not found (RUN_FOLDER: an ingest output; EVAL_FOLDER: an eval --record output)")
    clips = pq.read_table(f"{run}/clips.parquet").to_pydict()
    ids = clips["clip_id"]
    fps = dict(zip(ids, clips["fps"]))
    fr = pq.read_table(f"{run}/frames.parquet").select(
        ["clip_id", "frame", "obj_pos", "obj_linvel", "body_pos", "root_pos", "root_rot"]
    ).to_pydict()
    ref = {}
    keys = ["clip_id", "frame", "obj_pos", "obj_linvel", "body_pos", "root_pos", "root_rot"]
    for c, f, p, v, b, r, q in zip(*(fr[k] for k in keys)):
        if not p or not b:
            continue
        near = min(math.dist(p[:3], b[3 * k : 3 * k + 3]) for k in HAND_BODIES) < NEAR
        ref[(c, f)] = (p[2], v[2], near, p[:3], r, q)
    cols = ["metric", "trial", "step", "obj_pos", "ref_clip", "ref_frame", *extra]
    table = pq.read_table(f"{ev}/eval_rollouts.parquet")
    missing = [c for c in cols if c not in table.column_names]
    if missing:
        sys.exit(f"{os.path.basename(sys.argv[0])}: {ev}/eval_rollouts.parquet lacks {', '.join(missing)} (record it again with this skillaug)")
    ro = table.select(cols).to_pydict()
    trials = {}
    for row in zip(*(ro[k] for k in cols)):
        if row[0] == "sr":
            trials.setdefault(row[1], []).append(row[2:])
    if not trials:
        sys.exit(f"{ev}/eval_rollouts.parquet has no recorded SR trial")
    for t in trials:
        trials[t].sort(key=lambda x: x[0])
    return ids, fps, ref, trials


def catches(steps, ids, ref):
    """The positions in `steps` (one trial, in order) of its catches."""
    out = []
    bounced, prev_vz = False, None
    for i, (_, _, c, f, *_) in enumerate(steps):
        key = (ids[c], f) if c is not None else None
        if key not in ref:
            # a masked step or a missing frame: no reference to compare
            bounced, prev_vz = False, None
            continue
        z, vz, near = ref[key][:3]
        if prev_vz is not None and prev_vz <= 0 < vz and z < BOUNCE_BELOW:
            bounced = True
        if bounced and near:
            out.append(i)
            bounced = False
        prev_vz = vz
    return out


def main():
    args = [a for a in sys.argv[1:] if a != "-v"]
    verbose = "-v" in sys.argv[1:]
    if len(args) != 2:
        sys.exit(__doc__)
    ids, fps, ref, trials = load(*args)
    per_catch = {}
    for t in sorted(trials):
        steps = trials[t]
        line = []
        for k, i in enumerate(catches(steps, ids, ref)):
            s, p, c, f = steps[i][:4]
            z, vz = ref[(ids[c], f)][:2]
            prev = steps[i - 1][1] if i > 0 and steps[i - 1][0] == s - 1 else None
            sim_vz = (p[2] - prev[2]) * fps[ids[c]] if prev else float("nan")
            gap = p[2] - z
            rest = p[2] < 0.13 and abs(sim_vz) < 0.2
            per_catch.setdefault(k, []).append((gap, abs(gap) < REACHABLE, rest))
            line.append(f"step {s}: ball {p[2]:.2f} m ({sim_vz:+.1f} m/s), reference {z:.2f} m ({vz:+.1f} m/s)")
        if verbose:
            print(f"trial {t}: " + "; ".join(line))
    for k in sorted(per_catch):
        g = per_catch[k]
        n = len(g)
        print(
            f"catch {k + 1}: {n} trials, ball height minus the reference's {sum(x[0] for x in g) / n:+.2f} m, "
            f"within {REACHABLE} m {100 * sum(x[1] for x in g) / n:.0f} %, at rest {100 * sum(x[2] for x in g) / n:.0f} %"
        )


if __name__ == "__main__":
    main()
