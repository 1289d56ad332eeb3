#!/usr/bin/env python3
"""How the ball's bounce evolves in recorded dribble rollouts.

Usage: python3 stages/ball_apex.py EVAL_FOLDER [MIN_STANDING_STEPS]

EVAL_FOLDER holds eval_rollouts.parquet and eval_trials.parquet (from
`skillaug eval ... --set 'eval.metrics=["sr"]' --record N`). For every
recorded trial of the `sr` cell whose root stayed above the rule's height
for at least MIN_STANDING_STEPS steps (default 300), it prints the ball's
highest point in each 50-step window (m; the ball's radius, 0.12 m, is the
height of a ball at rest) and the first step from which the ball lay at
rest (below 0.15 m) for 30 steps, then the trial's success and mean SM
reward per step. Object 0 is the ball. Needs pyarrow and numpy (what
`.ci/run` installs), not pandas.
"""
import sys

import numpy as np
import pyarrow.parquet as pq


def main():
    ev = sys.argv[1]
    min_standing = int(sys.argv[2]) if len(sys.argv) > 2 else 300
    # pyarrow and numpy only (no pandas): columns as Python lists
    roll = pq.read_table(
        f"{ev}/eval_rollouts.parquet", columns=["metric", "trial", "step", "obj_pos"]
    ).to_pydict()
    trials = pq.read_table(
        f"{ev}/eval_trials.parquet", columns=["metric", "trial", "down_step", "success", "mean_sm"]
    ).to_pydict()
    paths = {}
    for m, t, s, p in zip(roll["metric"], roll["trial"], roll["step"], roll["obj_pos"]):
        if m == "sr":
            paths.setdefault(t, []).append((s, p[2]))
    keep = [
        (t, ok, sm)
        for m, t, d, ok, sm in zip(
            trials["metric"], trials["trial"], trials["down_step"], trials["success"], trials["mean_sm"]
        )
        if m == "sr" and t in paths and (d is None or d > min_standing)
    ]
    print(
        f"{len(keep)} of {len(paths)} recorded trials stood for more than "
        f"{min_standing} steps"
    )
    for t, ok, sm in sorted(keep):
        z = np.array([h for _, h in sorted(paths[t])])
        apex = [z[i : i + 50].max() for i in range(0, len(z), 50)]
        low = z < 0.15
        rest = next(
            (i for i in range(len(z) - 29) if low[i : i + 30].all()),
            None,
        )
        print(
            f"trial {t:3d}: apex per 50 steps "
            + " ".join(f"{a:.2f}" for a in apex)
            + f" | at rest from step {rest} | success {bool(ok)}, "
            f"mean SM {sm:.3f}"
        )


if __name__ == "__main__":
    main()
