#!/usr/bin/env python3
"""The simulated ball's spin as it lands, and what the bounce leaves of its speed.

Usage: python3 stages/bounce_spin.py EVAL_FOLDER [RADIUS]

EVAL_FOLDER holds eval_rollouts.parquet from `skillaug eval ... --set
'eval.metrics=["sr"]' --record N`; RADIUS is the ball's, m (0.12, the
BallPlay ball's, by default). For every recorded trial of the `sr` cell it
finds the bounces of the simulated ball (stages/bounce_times.py's
`bounces`: steps where its centre is at a local minimum below 0.2 m)
and, for each,
prints:
- the ball's horizontal speed two steps before and three steps after the
  bounce (from the recorded positions, 60 steps a second) and their ratio;
- its backspin as it lands, as a speed at its surface: the component of
  its angular velocity (from the recorded orientations of the two steps
  before) about the horizontal axis across its travel, times RADIUS,
  positive for backspin (the bottom of the ball moving forward), so a
  ball rolling forward has about minus its speed.
(Each trial's first six; a ball rolling on the floor counts a bounce at
every small dip of its height, as in stages/bounce_times.py.)
A solid sphere that lands with horizontal speed v and backspin b and
leaves the floor rolling keeps (5 v - 2 b) / 7: 5/7 of its speed without
spin, 0.52 of it (about what the captured DF ball keeps, 0.47-0.52 by
the frames read) with b = 0.68 v. Then, over all
trials, the means for each bounce in the list. Needs pyarrow only.
"""
import math
import sys

import pyarrow.parquet as pq

from bounce_times import bounces

DT = 1.0 / 60.0


def mul(a, b):
    """Product of two (x, y, z, w) quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def angular_velocity(q0, q1):
    """World-frame angular velocity taking q0 to q1 over one step, rad/s."""
    r = mul(q1, (-q0[0], -q0[1], -q0[2], q0[3]))
    if r[3] < 0:
        r = tuple(-x for x in r)
    n = math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2)
    if n == 0:
        return (0.0, 0.0, 0.0)
    angle = 2 * math.atan2(n, r[3])
    return tuple(r[k] / n * angle / DT for k in range(3))


def main():
    ev = sys.argv[1]
    radius = float(sys.argv[2]) if len(sys.argv) > 2 else 0.12
    ro = pq.read_table(f"{ev}/eval_rollouts.parquet").select(
        ["metric", "trial", "step", "obj_pos", "obj_rot"]
    ).to_pydict()
    trials = {}
    for m, t, s, p, q in zip(*(ro[k] for k in ["metric", "trial", "step", "obj_pos", "obj_rot"])):
        if m == "sr" and p and q:
            trials.setdefault(t, {})[s] = (p, q)
    by_bounce = {}
    for t in sorted(trials):
        d = trials[t]
        steps = sorted(d)
        cells = []
        for k, b in enumerate(bounces([d[s][0][2] for s in steps])):
            if b < 2 or b + 3 >= len(steps):
                continue
            (p0, q0), (p1, q1) = d[steps[b - 2]], d[steps[b - 1]]
            (p2, _), (p3, _) = d[steps[b + 2]], d[steps[b + 3]]
            v = [(p1[a] - p0[a]) / DT for a in range(2)]
            before = math.hypot(*v)
            after = math.hypot((p3[0] - p2[0]) / DT, (p3[1] - p2[1]) / DT)
            if before < 0.1:
                continue
            w = angular_velocity(q0, q1)
            # the axis across the travel, z x v: a ball rolling forward
            # spins about it positively; backspin is the opposite
            across = (-v[1] / before, v[0] / before)
            back = -(w[0] * across[0] + w[1] * across[1]) * radius
            by_bounce.setdefault(k + 1, []).append((after / before, back, before))
            cells.append(f"step {steps[b]}: {before:.2f} -> {after:.2f} m/s ({after / before:.2f}), backspin {back:+.2f} m/s")
        print(f"trial {t}: " + "; ".join(cells[:6]))
    for k in sorted(by_bounce)[:6]:
        r = by_bounce[k]
        n = len(r)
        print(
            f"bounce {k}: keeps {sum(x[0] for x in r) / n:.2f} of its horizontal speed, "
            f"lands at {sum(x[2] for x in r) / n:.2f} m/s with backspin {sum(x[1] for x in r) / n:+.2f} m/s "
            f"(mean of {n} trials)"
        )


if __name__ == "__main__":
    main()
