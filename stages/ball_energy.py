#!/usr/bin/env python3
"""The ball's mechanical energy against the reference ball's, by step.

Usage: python3 stages/ball_energy.py RUN_FOLDER EVAL_FOLDER

RUN_FOLDER is the `skillaug ingest` output (clips.parquet, frames.parquet); EVAL_FOLDER
holds eval_rollouts.parquet from `skillaug eval ... --record N`. For every
recorded step that is scored against a clip frame (not masked) and follows
a recorded step of the same trial, it computes the energy per unit mass
E = g z + |v|^2 / 2, J/kg, of the first object (the ball) in the
simulation (v by the difference of the recorded positions over one policy
step, 1/60 s) and in the clip at that frame (its stored velocity, also a
backward difference; the continued reference is moved about the vertical
only, so z and |v| are the clip's, except in the blended steps of
`train.seam_blend_steps`). It prints the mean and RMS of E - E_ref per 25
steps over the recorded trials of every cell: close to the gap that
`train.reward_weights = { oe = W }` scores (src/reward/mod.rs,
`Errors::oe`, which takes the simulated ball's own velocity). The first
bin starts at the first step with an earlier one. Needs pyarrow only.
"""
import math
import sys

import pyarrow.parquet as pq

G = 9.81  # the simulation's gravity, m/s^2 (src/sim/world.rs, GRAVITY)
STEP_S = 1.0 / 60.0


def energy(p, v):
    return G * p[2] + 0.5 * sum(x * x for x in v)


def main():
    run, ev = sys.argv[1], sys.argv[2]
    # a rollout's ref_clip is the clip's row in clips.parquet, as in bounce_times.py
    clip_ids = pq.read_table(f"{run}/clips.parquet").column("clip_id").to_pylist()
    f = pq.read_table(f"{run}/frames.parquet", columns=["clip_id", "frame", "obj_pos", "obj_linvel"]).to_pydict()
    ref = {}
    for c, i, p, v in zip(f["clip_id"], f["frame"], f["obj_pos"], f["obj_linvel"]):
        if p and v:
            ref[(c, i)] = energy(p[:3], v[:3])
    r = pq.read_table(f"{ev}/eval_rollouts.parquet").to_pydict()
    trials = {}
    for i in range(len(r["step"])):
        cell = (r["metric"][i], r["from_skill"][i], r["to_skill"][i], r["trial"][i])
        trials.setdefault(cell, []).append(i)
    gaps = {}
    for rows in trials.values():
        rows.sort(key=lambda i: r["step"][i])
        for a, b in zip(rows, rows[1:]):
            if r["step"][b] != r["step"][a] + 1 or r["masked"][b]:
                continue
            clip, frame = r["ref_clip"][b], r["ref_frame"][b]
            if clip is None or (clip_ids[clip], frame) not in ref:
                continue
            p0, p1 = r["obj_pos"][a][:3], r["obj_pos"][b][:3]
            if len(p0) < 3 or len(p1) < 3:
                continue
            v = [(y - x) / STEP_S for x, y in zip(p0, p1)]
            gaps.setdefault(r["step"][b] // 25, []).append(energy(p1, v) - ref[(clip_ids[clip], frame)])
    if not gaps:
        sys.exit(f"{ev}/eval_rollouts.parquet: no recorded step with a ball and a clip frame")
    print("steps     mean E - E_ref  RMS     n   (J/kg)")
    for k in sorted(gaps):
        d = gaps[k]
        mean = sum(d) / len(d)
        rms = math.sqrt(sum(x * x for x in d) / len(d))
        print(f"{25 * k:3d}-{25 * k + 24:3d}   {mean:7.2f}      {rms:6.2f}  {len(d)}")


if __name__ == "__main__":
    main()
