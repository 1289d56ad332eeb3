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
reward per step. Object 0 is the ball.
"""
import sys

import numpy as np
import pyarrow.parquet as pq


def main():
    ev = sys.argv[1]
    min_standing = int(sys.argv[2]) if len(sys.argv) > 2 else 300
    roll = pq.read_table(f"{ev}/eval_rollouts.parquet").to_pandas()
    roll = roll[roll.metric == "sr"]
    trials = pq.read_table(f"{ev}/eval_trials.parquet").to_pandas()
    trials = trials[trials.metric == "sr"]
    recorded = set(roll.trial.unique())
    keep = trials[
        trials.trial.isin(recorded)
        & (trials.down_step.isna() | (trials.down_step > min_standing))
    ]
    print(
        f"{len(keep)} of {len(recorded)} recorded trials stood for more than "
        f"{min_standing} steps"
    )
    for _, t in keep.iterrows():
        d = roll[roll.trial == t.trial].sort_values("step")
        z = np.array([o[2] for o in d.obj_pos.values])
        apex = [z[i : i + 50].max() for i in range(0, len(z), 50)]
        low = z < 0.15
        rest = next(
            (i for i in range(len(z) - 29) if low[i : i + 30].all()),
            None,
        )
        print(
            f"trial {t.trial:3d}: apex per 50 steps "
            + " ".join(f"{a:.2f}" for a in apex)
            + f" | at rest from step {rest} | success {bool(t.success)}, "
            f"mean SM {t.mean_sm:.3f}"
        )


if __name__ == "__main__":
    main()
