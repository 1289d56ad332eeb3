#!/usr/bin/env python3
"""Where the simulated ball is when the reference comes round to a frame.

Usage: python3 stages/ball_lead.py RUN_FOLDER EVAL_FOLDER CLIP_NAME FRAME

RUN_FOLDER is the `skillaug ingest` output (clips.parquet, frames.parquet);
EVAL_FOLDER holds eval_rollouts.parquet from `skillaug eval ... --set
'eval.metrics=["sr"]' --record N`. At every recorded step of the `sr` cell
that is scored against frame FRAME of clip CLIP_NAME (for DF's `run`, frame
34 is where the clip's hand meets its ball again after the first bounce,
`skillaug train` prints it as the push window's catch), it prints the
ball's position relative to the root in the root's heading frame (x_h
along the root's local x axis turned into the floor plane, the axis whose
angle the reference code's `calc_heading` takes, y_h across it, z the
height above the floor, m), beside the
reference's: the continued reference is the clip's frame moved about the
vertical, so its offset in its own heading frame is the clip's. Then, per
visit (the first, second, ... time a trial comes round to that frame), the
mean horizontal distance between the two offsets: about 0 while the ball
comes back to where the clip's hand meets it. Steps from a trial's first
with the root below 0.5 m on (a fall) are left out. Needs pyarrow only.
"""
import math
import sys

import pyarrow.parquet as pq


def heading(q):
    """Heading of an (x, y, z, w) quaternion: atan2 of the rotated x axis."""
    x, y, z, w = q
    # first column of the rotation matrix
    return math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def offset(root, q, ball):
    """`ball` relative to `root` in the heading frame of `q`, m."""
    h = heading(q)
    dx, dy = ball[0] - root[0], ball[1] - root[1]
    c, s = math.cos(h), math.sin(h)
    return (c * dx + s * dy, -s * dx + c * dy, ball[2])


def main():
    run, ev, name, frame = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    clips = pq.read_table(f"{run}/clips.parquet").to_pydict()
    if name not in clips["name"]:
        sys.exit(f"ball_lead: no clip named {name} in {run}/clips.parquet")
    cid = clips["clip_id"][clips["name"].index(name)]
    fr = pq.read_table(f"{run}/frames.parquet").select(
        ["clip_id", "frame", "root_pos", "root_rot", "obj_pos"]
    ).to_pydict()
    ref = None
    for c, f, r, q, o in zip(*(fr[k] for k in ["clip_id", "frame", "root_pos", "root_rot", "obj_pos"])):
        if c == cid and f == frame and o:
            ref = offset(r, q, o)
    if ref is None:
        sys.exit(f"ball_lead: clip {name} has no frame {frame} with a ball")
    print(f"reference at {name} frame {frame}: ball at x_h {ref[0]:+.2f}, y_h {ref[1]:+.2f}, z {ref[2]:.2f} m")
    ro = pq.read_table(f"{ev}/eval_rollouts.parquet").select(
        ["metric", "trial", "step", "root_pos", "root_rot", "obj_pos", "ref_clip", "ref_frame"]
    ).to_pydict()
    visits = {}
    per_trial = {}
    keys = ["metric", "trial", "step", "root_pos", "root_rot", "obj_pos", "ref_clip", "ref_frame"]
    fell = {}
    for m, t, s, r in zip(ro["metric"], ro["trial"], ro["step"], ro["root_pos"]):
        if m == "sr" and r[2] < 0.5:
            fell[t] = min(fell.get(t, s), s)
    for m, t, s, r, q, o, c, f in zip(*(ro[k] for k in keys)):
        if m == "sr" and c == cid and f == frame and o and s < fell.get(t, s + 1):
            per_trial.setdefault(t, []).append((s, offset(r, q, o)))
    for t in sorted(per_trial):
        seen = sorted(per_trial[t])
        cells = []
        for k, (s, p) in enumerate(seen):
            d = math.hypot(p[0] - ref[0], p[1] - ref[1])
            visits.setdefault(k + 1, []).append(d)
            cells.append(f"step {s}: {p[0]:+.2f} / {p[1]:+.2f} / {p[2]:.2f} ({d:.2f})")
        print(f"trial {t} (x_h / y_h / z, distance): " + "; ".join(cells))
    for k in sorted(visits)[:6]:
        d = visits[k]
        print(f"visit {k}: horizontal distance from the reference's offset {sum(d) / len(d):.2f} m (mean of {len(d)} trials)")


if __name__ == "__main__":
    main()
