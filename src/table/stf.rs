//! `stf_samples.parquet`: trajectories sampled from the State Transition
//! Field (paper Sections 4.3-4.5, Algorithm 1; algorithm in
//! [`crate::augment::stf`]), one row per (trajectory, step), so that a user
//! can inspect and plot what the trainer sees. Also the reader of the
//! optional ATS rewards table (`clip_id`, `frame`, `mean_reward`) and its
//! check against the clips of a run.

use super::columns::{specs, Column, TableRow};
use super::read_util::col;
use super::ColumnSpec;
use crate::augment::stf::Trajectory;
use anyhow::{anyhow, bail, Result};
use arrow::array::{Array, AsArray};
use arrow::datatypes::{
    DataType, Float32Type, Float64Type, Int16Type, Int32Type, Int64Type, Int8Type, UInt16Type,
    UInt32Type, UInt64Type, UInt8Type,
};
use arrow::record_batch::RecordBatch;
use std::path::Path;

/// One row of `stf_samples.parquet`: one step of a sampled trajectory, the
/// trajectory's values repeated on each of its rows and its start state
/// on step 0 only.
struct StfRow {
    traj_id: u32,
    step: u32,
    masked: bool,
    ref_clip: Option<u32>,
    ref_frame: Option<u32>,
    condition: u32,
    target_skill: String,
    start_kind: &'static str,
    fallback: bool,
    centroid: (u32, u32),
    beta: f64,
    n_masked: u32,
    start: Option<std::sync::Arc<crate::motion::State>>,
}

impl TableRow for StfRow {
    /// J = joints, B = bodies, O = objects (as in frames.parquet).
    /// Quaternions are (x, y, z, w).
    fn columns() -> Vec<Column<StfRow>> {
        type R = StfRow;
        macro_rules! start {
            ($name:literal, $field:ident, $doc:literal, fixed) => {
                Column::new($name, $doc, |r: &R| r.start.as_ref().map(|s| s.$field))
            };
            ($name:literal, $field:ident, $doc:literal, list) => {
                Column::new($name, $doc, |r: &R| {
                    r.start.as_ref().map(|s| s.$field.clone())
                })
            };
        }
        vec![
            Column::new("traj_id", "trajectory, 0-based in sampling order", |r: &R| r.traj_id),
            Column::new("step", "0 = the start state (the reset state, no reward); then one row per policy step, at most the horizon", |r: &R| r.step),
            Column::new("masked", "no reward at this step: an inserted masked state (ref null) or a missing reference frame (ref set)", |r: &R| r.masked),
            Column::new("ref_clip", "clip of the reference frame tracked at this step (clips.parquet clip_id); null at step 0 and for inserted masked states", |r: &R| r.ref_clip),
            Column::new("ref_frame", "frame of the reference frame tracked at this step", |r: &R| r.ref_frame),
            Column::new("condition", "condition: class id of the target skill A", |r: &R| r.condition),
            Column::new("target_skill", "skill A the trajectory tracks", |r: &R| r.target_skill.clone()),
            Column::new("start_kind", "rsi (a frame of A chosen by ATS), stg (an external state through an STG edge), rsi+noise or stg+noise (then drawn from the epsilon-neighbourhood)", |r: &R| r.start_kind),
            Column::new("fallback", "the sampled start had beta <= tau and was replaced by a plain reference frame of A (start_kind rsi)", |r: &R| r.fallback),
            Column::new("centroid_clip", "clip of the centroid state before noise: the ATS frame of A (rsi) or the STG edge's source frame (stg)", |r: &R| r.centroid.0),
            Column::new("centroid_frame", "frame of the centroid state", |r: &R| r.centroid.1),
            Column::new("beta", "similarity S_k (Eq. 19) of the start and the reference frame it connects to (Eq. 6 argmax); 1 for an unperturbed reference start", |r: &R| r.beta),
            Column::new("n_masked", "masked states N between start and reference (Eq. 20)", |r: &R| r.n_masked),
            start!("root_pos", root_pos, "start state (step 0 only): root world position, m", fixed),
            start!("root_rot", root_rot, "start: root world rotation, unit quaternion (x, y, z, w)", fixed),
            start!("root_rot_expmap", root_rot_expmap, "start: root world rotation, exp-map, rad", fixed),
            start!("root_linvel", root_linvel, "start: root linear velocity, m/s", fixed),
            start!("root_angvel", root_angvel, "start: root angular velocity, rad/s (frame as in frames.parquet)", fixed),
            start!("joint_rot", joint_rot, "start: [J*3] joint exp-maps, rad", list),
            start!("joint_vel", joint_vel, "start: [J*3] joint exp-map velocities, rad/s", list),
            start!("body_pos", body_pos, "start: [B*3] body world positions, m (under noise: stored positions plus the forward-kinematics change, or rigid with the root when sample-stf.fk = false)", list),
            start!("body_vel", body_vel, "start: [B*3] body linear velocities, m/s", list),
            start!("obj_pos", obj_pos, "start: [O*3] object positions, m", list),
            start!("obj_rot", obj_rot, "start: [O*4] object rotations, unit quaternions (x, y, z, w)", list),
            start!("obj_linvel", obj_linvel, "start: [O*3] object linear velocities, m/s", list),
            start!("obj_angvel", obj_angvel, "start: [O*3] object angular velocities, rad/s", list),
        ]
    }
}

/// The documented columns. J = joints, B = bodies, O = objects (as in
/// frames.parquet). Quaternions are (x, y, z, w). Per-trajectory values repeat
/// on every row of the trajectory; the start state is filled at step 0 only.
pub fn columns() -> Vec<ColumnSpec> {
    specs::<StfRow>()
}

/// The record batch of `trajs` (trajectory ids = positions).
pub fn batch(trajs: &[Trajectory]) -> Result<RecordBatch> {
    let mut rows = Vec::with_capacity(trajs.iter().map(|t| t.steps.len()).sum());
    for (id, t) in trajs.iter().enumerate() {
        let start = std::sync::Arc::new(t.start.clone());
        for (k, s) in t.steps.iter().enumerate() {
            rows.push(StfRow {
                traj_id: id as u32,
                step: k as u32,
                masked: s.masked,
                ref_clip: s.ref_clip,
                ref_frame: s.ref_frame,
                condition: t.condition,
                target_skill: t.target_skill.clone(),
                start_kind: t.kind_label(),
                fallback: t.fallback,
                centroid: t.centroid,
                beta: t.beta,
                n_masked: t.n_masked,
                start: (k == 0).then(|| start.clone()),
            });
        }
    }
    super::columns::batch(&rows)
}

/// An integer column as u64 values (any Arrow integer type, no nulls or
/// negatives).
fn ints(b: &RecordBatch, name: &str, path: &Path) -> Result<Vec<u64>> {
    let a = col(b, name, path)?;
    if a.null_count() > 0 {
        bail!("{}: column `{name}` has null values", path.display());
    }
    macro_rules! conv {
        ($t:ty) => {
            a.as_primitive::<$t>()
                .values()
                .iter()
                .map(|v| u64::try_from(*v).ok())
                .collect::<Option<Vec<u64>>>()
        };
    }
    let v = match a.data_type() {
        DataType::UInt8 => conv!(UInt8Type),
        DataType::UInt16 => conv!(UInt16Type),
        DataType::UInt32 => conv!(UInt32Type),
        DataType::UInt64 => conv!(UInt64Type),
        DataType::Int8 => conv!(Int8Type),
        DataType::Int16 => conv!(Int16Type),
        DataType::Int32 => conv!(Int32Type),
        DataType::Int64 => conv!(Int64Type),
        t => bail!(
            "{}: column `{name}` is {t:?}, expected an integer (UInt32)",
            path.display()
        ),
    };
    v.ok_or_else(|| anyhow!("{}: column `{name}` has negative values", path.display()))
}

/// One row of an ATS rewards table: the mean reward R̄ of the start frame
/// (Eq. 21) that `sample-stf.rewards` seeds the sampler with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RewardRow {
    /// Clip (clips.parquet clip_id).
    pub clip_id: u32,
    /// Start frame.
    pub frame: u32,
    /// Mean reward of episodes started there.
    pub mean_reward: f64,
}

/// Read an ATS rewards table: columns `clip_id` (UInt32; any integer type
/// is accepted), `frame` (UInt32) and `mean_reward` (Float64 or Float32), one
/// row per (clip, start frame).
pub fn read_rewards(path: &Path) -> Result<Vec<RewardRow>> {
    let t = super::io::read_parquet(path)?;
    let mut out = Vec::new();
    for b in &t.batches {
        let clip = ints(b, "clip_id", path)?;
        let frame = ints(b, "frame", path)?;
        let r = col(b, "mean_reward", path)?;
        if r.null_count() > 0 {
            bail!("{}: column `mean_reward` has null values", path.display());
        }
        let r: Vec<f64> = match r.data_type() {
            DataType::Float64 => r.as_primitive::<Float64Type>().values().to_vec(),
            DataType::Float32 => r
                .as_primitive::<Float32Type>()
                .values()
                .iter()
                .map(|v| *v as f64)
                .collect(),
            t => bail!(
                "{}: column `mean_reward` is {t:?}, expected Float64 or Float32",
                path.display()
            ),
        };
        for i in 0..b.num_rows() {
            let c = u32::try_from(clip[i]).map_err(|_| {
                anyhow!("{}: row {i}: clip_id {} too large", path.display(), clip[i])
            })?;
            let f = u32::try_from(frame[i]).map_err(|_| {
                anyhow!("{}: row {i}: frame {} too large", path.display(), frame[i])
            })?;
            if !r[i].is_finite() {
                bail!(
                    "{}: column `mean_reward`: row {i} (clip {c}, frame {f}) is {}",
                    path.display(),
                    r[i]
                );
            }
            out.push(RewardRow {
                clip_id: c,
                frame: f,
                mean_reward: r[i],
            });
        }
    }
    Ok(out)
}

/// Check the rows of an ATS rewards table ([`read_rewards`] of `path`)
/// against the clips of `lib`: every clip id a clip of `lib`, every frame
/// inside its clip, at most one row per (clip, frame).
///
/// # Errors
/// The first row that breaks one of those rules (the message names `path`
/// and the row).
pub fn check_rewards(
    path: &Path,
    rows: &[RewardRow],
    lib: &crate::motion::MotionLib,
) -> Result<()> {
    let mut seen = std::collections::BTreeSet::new();
    for (i, row) in rows.iter().enumerate() {
        let (c, f) = (&row.clip_id, &row.frame);
        let Some(cf) = lib.frames.get(*c as usize) else {
            bail!(
                "{}: row {i}: clip_id {c} is not a clip of this run ({} clips)",
                path.display(),
                lib.clips.len()
            );
        };
        if *f as usize >= cf.frames {
            bail!(
                "{}: row {i}: frame {f} is outside clip {c} ({} frames)",
                path.display(),
                cf.frames
            );
        }
        if !seen.insert((*c, *f)) {
            bail!(
                "{}: row {i}: a second row for clip {c}, frame {f}",
                path.display()
            );
        }
    }
    Ok(())
}

/// A trajectory of `stf_samples.parquet` as the viewer draws it.
#[derive(Clone, Debug, PartialEq)]
pub struct SampledTrajectory {
    /// `traj_id`.
    pub traj_id: u32,
    /// Skill A.
    pub target_skill: String,
    /// rsi, stg, rsi+noise or stg+noise.
    pub start_kind: String,
    /// S_k of the start and the frame it connects to.
    pub beta: f64,
    /// Masked states N.
    pub n_masked: u32,
    /// The start state's posture (step 0).
    pub start: crate::motion::state::Posture,
    /// Steps 1.. .
    pub steps: Vec<SampledStep>,
}

/// One step after the start of a [`SampledTrajectory`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SampledStep {
    /// The step has no reward target (one of the N masked states).
    pub masked: bool,
    /// Its reference frame (clip, frame); `None` when masked.
    pub reference: Option<(u32, u32)>,
}

/// Read the trajectories of an `stf_samples` table (rows grouped by
/// `traj_id`, step 0 first, as `sample-stf` writes them).
pub fn read_trajectories(path: &Path) -> Result<Vec<SampledTrajectory>> {
    use super::read_util::{bools, check_table, opt_u32s, posture_row, strs};
    let t = super::io::read_parquet(path)?;
    check_table(&t, path, "stf_samples")?;
    let mut out: Vec<SampledTrajectory> = Vec::new();
    for b in &t.batches {
        let u = |name: &str| opt_u32s(b, name, path);
        let (id, step, rc, rf, nm) = (
            u("traj_id")?,
            u("step")?,
            u("ref_clip")?,
            u("ref_frame")?,
            u("n_masked")?,
        );
        let masked = bools(b, "masked", path)?;
        let beta = col(b, "beta", path)?
            .as_primitive_opt::<Float64Type>()
            .ok_or_else(|| anyhow!("{}: column `beta` is not Float64", path.display()))?
            .clone();
        let (skill, kind) = (strs(b, "target_skill", path)?, strs(b, "start_kind", path)?);
        for i in 0..b.num_rows() {
            let bad = |what: &str| anyhow!("{}: row {i}: {what}", path.display());
            let tid = id[i].ok_or_else(|| bad("null traj_id"))?;
            if step[i] == Some(0) {
                out.push(SampledTrajectory {
                    traj_id: tid,
                    target_skill: skill[i].clone(),
                    start_kind: kind[i].clone(),
                    beta: beta.value(i),
                    n_masked: nm[i].unwrap_or(0),
                    start: posture_row(b, path, i)?
                        .ok_or_else(|| bad("step 0 without its start state"))?,
                    steps: Vec::new(),
                });
            } else {
                match out.last_mut() {
                    Some(t) if t.traj_id == tid => t.steps.push(SampledStep {
                        masked: masked[i],
                        reference: rc[i].zip(rf[i]),
                    }),
                    _ => return Err(bad("a step before its trajectory's step 0")),
                }
            }
        }
    }
    Ok(out)
}
