//! `eval_rollouts.parquet`: the simulated trials that `skillaug eval
//! --record N` keeps (the first N finished trials of each cell), one row per
//! (cell, trial, policy step), with the reference frame the step was scored
//! against, so that `skillaug view --rollouts` can play each trial beside its
//! reference.

use super::columns::{specs, Column, TableRow};
use super::read_util::{
    bools, check_table, col, opt_bools_if_present, opt_f32s_if_present, opt_f32x3s_if_present,
    opt_u32s, posture_row, strs,
};
use super::ColumnSpec;
use crate::motion::state::Posture;
use anyhow::{anyhow, Result};
use arrow::array::{Array, AsArray};
use arrow::datatypes::Float64Type;
use arrow::record_batch::RecordBatch;
use std::path::Path;

/// One recorded policy step of one trial.
#[derive(Clone, Debug, PartialEq)]
pub struct RolloutStep {
    /// sr, tsr, nsr or nr.
    pub metric: String,
    /// Start skill.
    pub from: String,
    /// Condition / rule skill.
    pub to: String,
    /// Trial number within the cell (as in eval_trials.parquet).
    pub trial: u32,
    /// Policy step, 1-based (the state after the step's action).
    pub step: u32,
    /// Reference frame the step was compared with (None: masked step or past
    /// the clip's end).
    pub reference: Option<(u32, u32)>,
    /// The step had no reward target.
    pub masked: bool,
    /// SM reward of the step (None when masked).
    pub sm_reward: Option<f64>,
    /// Simulated posture after the step.
    pub posture: Posture,
    /// Smallest distance from a hand body's origin to object 0's centre
    /// over the step's physics substeps, m (None: no object, or a table
    /// written before the column existed).
    pub hand_ball_distance: Option<f32>,
    /// A hand body touched object 0 at any physics substep of the step
    /// (None: no object, or an older table).
    pub hand_ball_touch: Option<bool>,
    /// With `train.hand_follows_ball`, inside a push window proper: the
    /// pushing hand body's distance after the step from the point its
    /// targets were solved towards, m (None: outside, off, or an older
    /// table).
    pub hand_target_distance: Option<f32>,
    /// At the same steps: the point the pushing hand's targets were solved
    /// towards before the step, world frame, m (None: outside, off, or an
    /// older table).
    pub hand_target: Option<[f32; 3]>,
    /// At the same steps: where the feed-forward targets (the solved pose
    /// as the drives get it) put the pushing hand body, from the simulated
    /// root before the step, world frame, m.
    pub hand_target_posed: Option<[f32; 3]>,
    /// At the same steps: where the targets the step applied (the
    /// feed-forward plus the policy's residual) put that body, from the
    /// same root, world frame, m.
    pub hand_target_applied: Option<[f32; 3]>,
    /// At the same steps: the pushing hand body's origin after the step,
    /// world frame, m (None: outside, off, or an older table).
    pub pushing_hand_pos: Option<[f32; 3]>,
}

impl TableRow for RolloutStep {
    /// J joints, O objects; quaternions x, y, z, w.
    fn columns() -> Vec<Column<RolloutStep>> {
        type R = RolloutStep;
        vec![
            Column::new("metric", "sr, tsr, nsr or nr (the eval cell)", |r: &R| r.metric.clone()),
            Column::new("from_skill", "start skill of the cell", |r: &R| r.from.clone()),
            Column::new("to_skill", "condition / rule skill of the cell", |r: &R| r.to.clone()),
            Column::new("trial", "trial within the cell, as in eval_trials.parquet", |r: &R| r.trial),
            Column::new("step", "policy step, 1-based: the simulated state after the step's action", |r: &R| r.step),
            Column::new("ref_clip", "clip of the reference frame the step was scored against (clips.parquet clip_id); null when masked or past the clip's end; for a policy evaluated with its reference continued (train.residual_action, train.reference_obs) the continued clip's frame, which the trial sees moved to the character and blended after a seam", |r: &R| r.reference.map(|x| x.0)),
            Column::new("ref_frame", "frame of that reference frame", |r: &R| r.reference.map(|x| x.1)),
            Column::new("masked", "the step had no reward target", |r: &R| r.masked),
            Column::new("sm_reward", "SM reward of the step; null when masked", |r: &R| r.sm_reward),
            Column::new("root_pos", "simulated root world position, m", |r: &R| r.posture.root_pos),
            Column::new("root_rot", "simulated root world rotation, unit quaternion (x, y, z, w)", |r: &R| r.posture.root_rot),
            Column::new("joint_rot", "[J*3] simulated joint exp-maps, rad", |r: &R| r.posture.joint_rot.clone()),
            Column::new("obj_pos", "[O*3] simulated object positions, m", |r: &R| r.posture.obj_pos.clone()),
            Column::new("obj_rot", "[O*4] simulated object rotations (x, y, z, w)", |r: &R| r.posture.obj_rot.clone()),
            Column::new("hand_ball_distance", "smallest distance from a hand body's origin (wrist or finger joint) to object 0's centre over the step's physics substeps, m; null without an object", |r: &R| r.hand_ball_distance),
            Column::new("hand_ball_touch", "a hand body's collider touched object 0 at any physics substep of the step; null without an object", |r: &R| r.hand_ball_touch),
            Column::new("hand_target_distance", "with train.hand_follows_ball, at a step whose reference frame is inside a push window proper (weight 1): the distance from the pushing hand body's origin after the step to the point its targets were solved towards (above the simulated ball, within train.hand_follows_ball_reach of the reference's hand), m; null otherwise", |r: &R| r.hand_target_distance),
            Column::new("hand_target", "at the steps of hand_target_distance: the point the pushing hand's targets were solved towards before the step (above the simulated ball, led by 0.1 s of the reference ball's motion relative to its root, the drives' time constant, and capped at train.hand_follows_ball_reach from the reference's hand), world frame, m; null otherwise", |r: &R| r.hand_target),
            Column::new("hand_target_posed", "at the same steps: where the feed-forward targets (the pose solved towards hand_target, as the drives get it: clamped to +-pi, with a push offset where one applies) put the pushing hand body (forward kinematics from the simulated root before the step; its distance from hand_target is the solver's residual), world frame, m; null otherwise", |r: &R| r.hand_target_posed),
            Column::new("hand_target_applied", "at the same steps: where the joint targets the step applied (the feed-forward of hand_target_posed plus the policy's residual) put the pushing hand body, from the same root, world frame, m; null otherwise", |r: &R| r.hand_target_applied),
            Column::new("pushing_hand_pos", "at the same steps: the pushing hand body's origin after the step, world frame, m; null otherwise", |r: &R| r.pushing_hand_pos),
        ]
    }
}

/// The documented columns (J joints, O objects; quaternions x, y, z, w).
pub fn columns() -> Vec<ColumnSpec> {
    specs::<RolloutStep>()
}

/// The record batch of `rows`.
pub fn batch(rows: &[RolloutStep]) -> Result<RecordBatch> {
    super::columns::batch(rows)
}

/// Read a rollouts table back.
pub fn read(path: &Path) -> Result<Vec<RolloutStep>> {
    let t = super::io::read_parquet(path)?;
    check_table(&t, path, "eval_rollouts")?;
    let mut out = Vec::with_capacity(t.rows());
    for b in &t.batches {
        let (metric, from, to) = (
            strs(b, "metric", path)?,
            strs(b, "from_skill", path)?,
            strs(b, "to_skill", path)?,
        );
        let u = |name: &str| opt_u32s(b, name, path);
        let (trial, step, rc, rf) = (u("trial")?, u("step")?, u("ref_clip")?, u("ref_frame")?);
        let masked = bools(b, "masked", path)?;
        // tables written before these columns existed lack them
        let distance = opt_f32s_if_present(b, "hand_ball_distance", path)?;
        let touch = opt_bools_if_present(b, "hand_ball_touch", path)?;
        let aim = opt_f32s_if_present(b, "hand_target_distance", path)?;
        let target = opt_f32x3s_if_present(b, "hand_target", path)?;
        let posed = opt_f32x3s_if_present(b, "hand_target_posed", path)?;
        let applied = opt_f32x3s_if_present(b, "hand_target_applied", path)?;
        let hand = opt_f32x3s_if_present(b, "pushing_hand_pos", path)?;
        let sm = col(b, "sm_reward", path)?
            .as_primitive_opt::<Float64Type>()
            .ok_or_else(|| anyhow!("{}: column `sm_reward` is not Float64", path.display()))?
            .clone();
        for i in 0..b.num_rows() {
            let bad = |n: &str| anyhow!("{}: row {i}: `{n}` is null", path.display());
            out.push(RolloutStep {
                metric: metric[i].clone(),
                from: from[i].clone(),
                to: to[i].clone(),
                trial: trial[i].ok_or_else(|| bad("trial"))?,
                step: step[i].ok_or_else(|| bad("step"))?,
                reference: rc[i].zip(rf[i]),
                masked: masked[i],
                sm_reward: sm.is_valid(i).then(|| sm.value(i)),
                posture: posture_row(b, path, i)?.ok_or_else(|| bad("root_pos"))?,
                hand_ball_distance: distance[i],
                hand_ball_touch: touch[i],
                hand_target_distance: aim[i],
                hand_target: target[i],
                hand_target_posed: posed[i],
                hand_target_applied: applied[i],
                pushing_hand_pos: hand[i],
            });
        }
    }
    Ok(out)
}
