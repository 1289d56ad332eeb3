#!/usr/bin/env python3
"""When the simulated ball bounces, against the reference's ball.

Usage: python3 stages/bounce_times.py RUN_FOLDER EVAL_FOLDER

RUN_FOLDER is the `skillaug ingest` output (clips.parquet, frames.parquet);
EVAL_FOLDER holds eval_rollouts.parquet from `skillaug eval ... --set
'eval.metrics=["sr"]' --record N`. For every recorded trial of the `sr`
cell it finds the bounces (steps where the ball's centre is at a local
minimum below 0.2 m) of the simulated ball and of the reference's ball
(the clip frame each step was scored against; the continued reference is
moved about the vertical only, so its height is the clip's), and prints
both lists. Then, over all trials, the flight time between consecutive
bounces of the simulated ball divided by the reference's flight time at
the same place in the list: about 1 while the policy feeds the ball as
the clip does, the ball's restitution (0.805) per bounce for a ball left
to bounce on its own. Needs pyarrow only.
"""
import sys

import pyarrow.parquet as pq


def bounces(z):
    return [i for i in range(1, len(z) - 1) if z[i] < 0.2 and z[i] <= z[i - 1] and z[i] < z[i + 1]]


def main():
    run, ev = sys.argv[1], sys.argv[2]
    clip_ids = pq.read_table(f"{run}/clips.parquet").column("clip_id").to_pylist()
    fr = pq.read_table(f"{run}/frames.parquet").select(["clip_id", "frame", "obj_pos"]).to_pydict()
    ref_z = {
        (c, f): p[2]
        for c, f, p in zip(fr["clip_id"], fr["frame"], fr["obj_pos"])
        if p
    }
    ro = pq.read_table(f"{ev}/eval_rollouts.parquet").select(
        ["metric", "trial", "step", "obj_pos", "ref_clip", "ref_frame"]
    ).to_pydict()
    trials = {}
    for m, t, s, p, c, f in zip(*(ro[k] for k in ["metric", "trial", "step", "obj_pos", "ref_clip", "ref_frame"])):
        if m == "sr":
            trials.setdefault(t, []).append((s, p[2], c, f))
    ratios = {}
    for t in sorted(trials):
        steps = sorted(trials[t])
        sim = [z for _, z, _, _ in steps]
        # a masked step has no reference frame: it cannot be a bounce
        ref = [ref_z.get((clip_ids[c], f), 9.0) if c is not None else 9.0 for _, _, c, f in steps]
        bs, br = bounces(sim), bounces(ref)
        print(f"trial {t}: simulated ball bounces at {bs[:8]}, the reference's at {br[:8]}")
        for k in range(min(len(bs), len(br)) - 1):
            ratios.setdefault(k + 1, []).append((bs[k + 1] - bs[k]) / (br[k + 1] - br[k]))
    for k in sorted(ratios)[:6]:
        r = ratios[k]
        print(f"flight {k}: simulated / reference flight time {sum(r) / len(r):.2f} (mean of {len(r)} trials)")


if __name__ == "__main__":
    main()
