//! `eval_rollouts.parquet`: the simulated trials that `skillaug eval
//! --record N` keeps (the first N finished trials of each cell), one row per
//! (cell, trial, policy step), with the reference frame the step was scored
//! against, so that `skillaug view --rollouts` can play each trial beside its
//! reference.

use super::columns::F32Rows;
use super::read_util::{bools, check_table, col, opt_u32s, posture_row, strs};
use super::{f32_fixed, f32_list, schema_of, ColumnSpec};
use crate::motion::state::Posture;
use anyhow::{anyhow, Result};
use arrow::array::{
    Array, ArrayRef, AsArray, BooleanArray, Float64Array, StringArray, UInt32Array,
};
use arrow::datatypes::{DataType, Float64Type};
use arrow::record_batch::RecordBatch;
use std::path::Path;
use std::sync::Arc;

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
}

/// The documented columns (J joints, O objects; quaternions x, y, z, w).
pub fn columns() -> Vec<ColumnSpec> {
    use DataType::*;
    vec![
        ColumnSpec::new("metric", Utf8, false, "sr, tsr, nsr or nr (the eval cell)"),
        ColumnSpec::new("from_skill", Utf8, false, "start skill of the cell"),
        ColumnSpec::new("to_skill", Utf8, false, "condition / rule skill of the cell"),
        ColumnSpec::new("trial", UInt32, false, "trial within the cell, as in eval_trials.parquet"),
        ColumnSpec::new("step", UInt32, false, "policy step, 1-based: the simulated state after the step's action"),
        ColumnSpec::new("ref_clip", UInt32, true, "clip of the reference frame the step was scored against (clips.parquet clip_id); null when masked or past the clip's end; for a policy evaluated with its reference continued (train.residual_action, train.reference_obs) the continued clip's frame, which the trial sees moved to the character and blended after a seam"),
        ColumnSpec::new("ref_frame", UInt32, true, "frame of that reference frame"),
        ColumnSpec::new("masked", Boolean, false, "the step had no reward target"),
        ColumnSpec::new("sm_reward", Float64, true, "SM reward of the step; null when masked"),
        ColumnSpec::new("root_pos", f32_fixed(3), false, "simulated root world position, m"),
        ColumnSpec::new("root_rot", f32_fixed(4), false, "simulated root world rotation, unit quaternion (x, y, z, w)"),
        ColumnSpec::new("joint_rot", f32_list(), false, "[J*3] simulated joint exp-maps, rad"),
        ColumnSpec::new("obj_pos", f32_list(), false, "[O*3] simulated object positions, m"),
        ColumnSpec::new("obj_rot", f32_list(), false, "[O*4] simulated object rotations (x, y, z, w)"),
    ]
}

/// The record batch of `rows`.
pub fn batch(rows: &[RolloutStep]) -> Result<RecordBatch> {
    let s = |f: fn(&RolloutStep) -> &str| -> ArrayRef {
        Arc::new(StringArray::from_iter_values(rows.iter().map(f)))
    };
    let u = |f: fn(&RolloutStep) -> Option<u32>| -> ArrayRef {
        Arc::new(UInt32Array::from(rows.iter().map(f).collect::<Vec<_>>()))
    };
    let mut f: Vec<F32Rows> = vec![
        F32Rows::fixed(3),
        F32Rows::fixed(4),
        F32Rows::list(),
        F32Rows::list(),
        F32Rows::list(),
    ];
    for r in rows {
        let p = &r.posture;
        let parts: [&[f32]; 5] = [
            &p.root_pos,
            &p.root_rot,
            &p.joint_rot,
            &p.obj_pos,
            &p.obj_rot,
        ];
        for (c, v) in f.iter_mut().zip(parts) {
            c.push(Some(v));
        }
    }
    let mut arrays: Vec<ArrayRef> = vec![
        s(|r| &r.metric),
        s(|r| &r.from),
        s(|r| &r.to),
        u(|r| Some(r.trial)),
        u(|r| Some(r.step)),
        u(|r| r.reference.map(|x| x.0)),
        u(|r| r.reference.map(|x| x.1)),
        Arc::new(BooleanArray::from(
            rows.iter().map(|r| r.masked).collect::<Vec<_>>(),
        )),
        Arc::new(Float64Array::from(
            rows.iter().map(|r| r.sm_reward).collect::<Vec<_>>(),
        )),
    ];
    arrays.extend(f.into_iter().map(F32Rows::finish));
    Ok(RecordBatch::try_new(schema_of(&columns()), arrays)?)
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
            });
        }
    }
    Ok(out)
}
