#!/usr/bin/env python3
"""Where the captured hand is while a clip's ball speeds up.

Usage: python3 stages/hand_on_ball.py RUN_FOLDER CLIP_NAME FIRST LAST

RUN_FOLDER is the `skillaug ingest` output of a BallPlay dataset
(clips.parquet, frames.parquet; body order of `mocap_humanoid.xml`). For
frames FIRST..=LAST of clip CLIP_NAME it prints, for the hand whose wrist
is nearer the ball: the ball's height and vertical velocity, the wrist's
distance from the ball's centre and vertical velocity (backward
differences, the `body_vel` column), the palm's centre (the mean of the
wrist and the first joints of the index and little fingers) and how far
below the palm's plane and how far along it the ball's centre lies, and
the nearest fingertip's distance from the ball's centre (radius 0.12 m).
docs/training.md, "The clip's own motion does not keep its ball", quotes
it for DF `run` frames 3-11. Needs pyarrow only.
"""
import math
import sys

import pyarrow.parquet as pq

# Body indices in mocap_humanoid.xml order (src/motion/layout.rs).
HANDS = {
    "left": {"wrist": 18, "index1": 19, "pinky1": 25, "tips": [21, 24, 27, 30, 33]},
    "right": {"wrist": 37, "index1": 38, "pinky1": 44, "tips": [40, 43, 46, 49, 52]},
}


def sub(a, b):
    return [x - y for x, y in zip(a, b)]


def dot(a, b):
    return sum(x * y for x, y in zip(a, b))


def norm(a):
    return math.sqrt(dot(a, a))


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def main():
    if len(sys.argv) != 5:
        sys.exit(__doc__)
    run, name, first, last = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    clips = pq.read_table(f"{run}/clips.parquet").to_pylist()
    ids = [c["clip_id"] for c in clips if c["name"] == name]
    if not ids:
        sys.exit(f"{run}/clips.parquet: no clip named {name}")
    rows = [
        r
        for r in pq.read_table(f"{run}/frames.parquet").to_pylist()
        if r["clip_id"] == ids[0] and first <= r["frame"] <= last
    ]
    if not rows:
        sys.exit(f"{run}/frames.parquet: clip {name} has no frames {first}..={last}")
    print("frame  ball z  ball vz  hand   wrist d  wrist vz  palm d  below palm  along palm  fingertip d")
    for r in sorted(rows, key=lambda r: r["frame"]):
        if not r["valid"] or not r["obj_pos"]:
            print(f"{r['frame']:5d}  missing frame or no ball")
            continue
        ball = r["obj_pos"][:3]
        pos = lambda i: r["body_pos"][3 * i : 3 * i + 3]
        side, h = min(HANDS.items(), key=lambda kv: norm(sub(pos(kv[1]["wrist"]), ball)))
        w, i1, p1 = pos(h["wrist"]), pos(h["index1"]), pos(h["pinky1"])
        n = cross(sub(i1, w), sub(p1, w))
        n = [x / norm(n) for x in n]
        palm = [(a + b + c) / 3 for a, b, c in zip(w, i1, p1)]
        d = sub(ball, palm)
        below = abs(dot(d, n))
        along = math.sqrt(max(dot(d, d) - below * below, 0.0))
        tip = min(norm(sub(pos(t), ball)) for t in h["tips"])
        print(
            f"{r['frame']:5d}  {ball[2]:6.3f}  {r['obj_linvel'][2]:+7.2f}  {side:5s}  {norm(sub(w, ball)):7.3f}"
            f"  {r['body_vel'][3 * h['wrist'] + 2]:+8.2f}  {norm(d):6.3f}  {below:10.3f}  {along:10.3f}  {tip:11.3f}"
        )


if __name__ == "__main__":
    main()
