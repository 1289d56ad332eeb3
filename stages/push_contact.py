#!/usr/bin/env python3
"""Whether the simulated hand meets and pushes the ball after each catch.

Usage: python3 stages/push_contact.py RUN_FOLDER EVAL_FOLDER [-v]

RUN_FOLDER is the `skillaug ingest` output the policy was trained on,
EVAL_FOLDER a `skillaug eval --record N` output whose eval_rollouts.parquet
has the `hand_ball_distance` and `hand_ball_touch` columns (recorded by a
skillaug that writes them).

For every **catch** of a recorded SR trial (the step whose reference frame
is the first, after the reference's ball has bounced, where a hand body of
the clip is within 0.15 m of the clip's ball; `stages/catch_gap.py`) at
which the character still stands (root above 0.5 m), the script follows
the trial until the **push is over**: the first later step at which the
simulated ball is falling below 0.5 m (it then falls freely to the
floor), or the next catch, or the trial's end. It reads:

- the horizontal miss at the catch: the ball's offset from the root in
  the root's heading frame (`stages/ball_lead.py`) minus the clip frame's
  own, about 0 while the ball comes back to where the clip's hand meets
  it;
- touch: whether a hand body's collider touched the ball at some physics
  substep of any step until the push is over, and the share of such steps;
- the smallest distance of a hand body's origin to the ball's centre;
- the work done on the ball per unit mass, J/kg: the change of
  E = g z + |v|^2 / 2 from the catch to the push's end (velocities by
  backward differences of the recorded positions, at the clip's rate). A
  free flight keeps E; a push adds to it; a hand that rides the ball
  without pushing takes from it. The reference's ball over the same
  reference frames (backward differences of the clip's positions) gives
  the clip's own figure.

It prints, per catch (first, second, ...), the standing trials that reach
it, the median horizontal miss, the share with any touch, the mean share
of touching steps, the median smallest distance, and the mean work done
on the simulated and on the reference ball. With `-v`, every trial's
catches.

For a policy trained with `train.hand_follows_ball`, whose recording has
the `hand_target_distance` column, it then prints how far the pushing
hand ended, after each standing step inside a push window, from the point
its online targets aimed at (above the simulated ball, capped at
`train.hand_follows_ball_reach` from the reference's hand): the median
and the quartiles. That point leads the simulated ball by the drives'
time constant (0.1 s of the reference ball's motion relative to the
root), so a hand that follows its targets with the drives' lag is about
the lead's length from it after one step.

With the `hand_target`, `hand_target_posed`, `hand_target_applied` and
`pushing_hand_pos` columns it goes on, with medians over the standing
steps that aim:

- the solver's residual: from the aimed point to where the feed-forward
  targets (the solved pose as the drives get it) put the hand;
- the policy's shift: from there to where the applied targets (the
  feed-forward plus the policy's residual) put it (both from the same
  root, so no frame is needed);
- for k = 0 to the lead's steps less one (k + 1 steps after the targets
  were set; the last is the lead's time), the hand after step t + k from
  step t's aimed point, feed-forward pose and applied targets, in the
  root's frame (the targets are joint rotations, so the points they aim
  at move with the root), over runs of standing steps that all aim: how
  close the hand comes once the drives have had their time, and whether
  a gap is the solver's, the policy's or the drives'.

Needs pyarrow only.
"""
import math
import statistics
import sys

import pyarrow.parquet as pq

from ball_energy import energy
from ball_lead import offset
from catch_gap import catches, load

FALLING_BELOW = 0.5  # m: a ball falling below this height is on its way to the floor
STANDING = 0.5  # m: a root above this height stands (the evaluation's fall rule)
LEAD_S = 0.1  # s: the online hand target's lead (REACH_LEAD_S, src/sim/hand_path.rs)


def moving_energy(p, q, rate):
    """E per unit mass at ball position p, with the backward-difference
    velocity (p - q) * rate."""
    return energy(p, [(a - b) * rate for a, b in zip(p[:3], q[:3])])


def clip_energy(ref, ids, step, rate):
    """The clip ball's E at a recorded step's reference frame, from the
    frame and the one before it; None where either is missing."""
    c, f = step[2], step[3]
    if c is None or (ids[c], f) not in ref or (ids[c], f - 1) not in ref:
        return None
    return moving_energy(ref[(ids[c], f)][3], ref[(ids[c], f - 1)][3], rate)


def push_end(steps, i, nxt):
    """The last step of the push that starts at catch position i: the first
    later step whose ball falls below FALLING_BELOW, else the step before
    the next catch (position nxt) or the trial's end."""
    end = i + 1
    while end < nxt:
        p, q = steps[end][1], steps[end - 1][1]
        if p[2] < FALLING_BELOW and p[2] < q[2]:
            return end
        end += 1
    return nxt - 1


def main():
    args = [a for a in sys.argv[1:] if a != "-v"]
    verbose = "-v" in sys.argv[1:]
    if len(args) != 2:
        sys.exit(__doc__)
    ids, fps, ref, trials = load(*args, extra=("hand_ball_distance", "hand_ball_touch", "root_pos", "root_rot"))
    per_catch = {}
    for t in sorted(trials):
        steps = trials[t]
        at = catches(steps, ids, ref)
        line = []
        for k, i in enumerate(at):
            _, ball, c, f, _, _, root, rot = steps[i]
            if root[2] <= STANDING:
                # fallen: no hand to meet the ball
                per_catch.setdefault(k, [])
                line.append(f"step {steps[i][0]}: fallen")
                continue
            end = push_end(steps, i, at[k + 1] if k + 1 < len(at) else len(steps))
            window = steps[i : end + 1]
            if end <= i or i == 0 or any(s[0] != steps[i][0] + j for j, s in enumerate(window)):
                continue  # too short, or a gap in the recording
            rate = fps[ids[c]]
            touch = [bool(s[5]) for s in window]
            dist = min(s[4] for s in window)
            sim_work = moving_energy(steps[end][1], steps[end - 1][1], rate) - moving_energy(
                ball, steps[i - 1][1], rate
            )
            e0, e1 = clip_energy(ref, ids, steps[i], rate), clip_energy(ref, ids, steps[end], rate)
            ref_work = e1 - e0 if e0 is not None and e1 is not None else None
            r = ref[(ids[c], f)]
            a, b = offset(root, rot, ball), offset(r[4], r[5], r[3])
            miss = math.hypot(a[0] - b[0], a[1] - b[1])
            per_catch.setdefault(k, []).append((any(touch), sum(touch) / len(touch), dist, sim_work, ref_work, miss))
            line.append(
                f"steps {steps[i][0]}-{steps[end][0]}: touching {sum(touch)}/{len(touch)}, nearest {dist:.3f} m, "
                f"work {sim_work:+.1f} J/kg (reference {'-' if ref_work is None else f'{ref_work:+.1f}'}), "
                f"horizontal miss {miss:.2f} m"
            )
        if verbose:
            print(f"trial {t}: " + "; ".join(line))
    for k in sorted(per_catch):
        g = per_catch[k]
        n = len(g)
        if not g:
            print(f"catch {k + 1}: no trial standing")
            continue
        refs = [x[4] for x in g if x[4] is not None]
        ref_mean = f"{sum(refs) / len(refs):+.1f}" if refs else "-"
        print(
            f"catch {k + 1}: {n} standing trials, horizontal miss {statistics.median(x[5] for x in g):.2f} m (median), touched in {100 * sum(x[0] for x in g) / n:.0f} %, "
            f"{100 * sum(x[1] for x in g) / n:.0f} % of the push's steps; nearest hand "
            f"{statistics.median(x[2] for x in g):.3f} m (median); work on the ball "
            f"{sum(x[3] for x in g) / n:+.1f} J/kg, the reference's {ref_mean}"
        )
    online_target(args[1], fps)


def online_target(ev, fps):
    """Print the pushing hand's distance from its online target over the
    standing steps that have one, when the recording has the column; with
    the recorded points, where the gap comes from (see the module doc)."""
    path = f"{ev}/eval_rollouts.parquet"
    names = pq.read_schema(path).names
    if "hand_target_distance" not in names:
        return
    extra = ["hand_target", "hand_target_posed", "hand_target_applied", "pushing_hand_pos", "root_rot"]
    points = all(n in names for n in extra)
    cols = ["metric", "from_skill", "to_skill", "trial", "step", "root_pos", "hand_target_distance"]
    ro = pq.read_table(path, columns=cols + (extra if points else [])).to_pydict()
    rows = [
        i
        for i, (m, r, x) in enumerate(zip(ro["metric"], ro["root_pos"], ro["hand_target_distance"]))
        if m == "sr" and x is not None and r[2] > STANDING
    ]
    d = sorted(ro["hand_target_distance"][i] for i in rows)
    if not d:
        print("online hand: no standing step inside a push window (trained without hand_follows_ball?)")
        return
    q = quartiles(d)
    print(
        f"online hand: {len(d)} standing steps inside a push window; the hand ended {q[1]:.3f} m "
        f"(median; quartiles {q[0]:.3f}-{q[2]:.3f} m) from the point its targets aimed at"
    )
    if not points:
        return
    if len(set(fps.values())) != 1:
        print("online hand: the clips have different rates, so the lead's steps are not one number; stopping here")
        return
    # in the frame of the root: the targets are joint rotations, so a
    # point aimed at from the root before step t moves with the root
    # afterwards; the root before step t is the one recorded after t - 1
    def key(i, step=None):
        return (ro["from_skill"][i], ro["to_skill"][i], ro["trial"][i], ro["step"][i] if step is None else step)

    at = {key(i): i for i, m in enumerate(ro["metric"]) if m == "sr"}

    def local(i, p):
        return to_root(ro["root_pos"][i], ro["root_rot"][i], p)

    aims = {}
    for i in rows:
        k = key(i)
        before = at.get(key(i, k[3] - 1))
        pts = [ro[c][i] for c in ("hand_target", "hand_target_posed", "hand_target_applied")]
        if before is not None and all(p is not None for p in pts):
            aims[k] = [local(before, p) for p in pts]
    if not aims:
        return
    solver = [math.dist(a, b) for a, b, _ in aims.values()]
    policy = [math.dist(b, c) for _, b, c in aims.values()]
    print(
        f"online hand, over {len(aims)} steps (median): the feed-forward pose puts the hand "
        f"{statistics.median(solver):.3f} m from the aimed point; the policy's residual moves it "
        f"{statistics.median(policy):.3f} m from there"
    )
    # k = 0 is the hand one step after the targets were set, k = lead - 1
    # the lead's time after
    lead = round(LEAD_S * next(iter(fps.values())))
    for k in range(lead):
        g = []
        for (fr, to, t, s), pts in aims.items():
            later = at.get((fr, to, t, s + k))
            if later is not None and all((fr, to, t, s + j) in aims for j in range(1, k + 1)):
                h = local(later, ro["pushing_hand_pos"][later])
                g.append([math.dist(p, h) for p in pts])
        if g:
            print(
                f"  in the root's frame, hand after step t + {k} ({k + 1} steps) from step t's aimed point / "
                "feed-forward pose / applied targets: "
                + " / ".join(f"{statistics.median(x[c] for x in g):.3f}" for c in range(3))
                + f" m ({len(g)} steps)"
            )


def to_root(root, q, p):
    """Point `p` (m, world) in the frame of a root at `root` with rotation
    `q` (x, y, z, w): the inverse rotation of p - root."""
    x, y, z, w = q
    v = [p[k] - root[k] for k in range(3)]
    # v' = conj(q) v q, by t = 2 (u x v) with u = -(x, y, z)
    u = (-x, -y, -z)
    t = [2 * (u[1] * v[2] - u[2] * v[1]), 2 * (u[2] * v[0] - u[0] * v[2]), 2 * (u[0] * v[1] - u[1] * v[0])]
    c = [u[1] * t[2] - u[2] * t[1], u[2] * t[0] - u[0] * t[2], u[0] * t[1] - u[1] * t[0]]
    return [v[k] + w * t[k] + c[k] for k in range(3)]


def quartiles(d):
    """First, second and third quartiles of a non-empty list."""
    return statistics.quantiles(d, n=4) if len(d) > 1 else [d[0]] * 3


if __name__ == "__main__":
    main()
