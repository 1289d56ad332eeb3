//! `frames.parquet`: one row per clip frame, the reference states every later
//! stage reads. Derivations follow the reference loader,
//! Ingrid789/SkillMimic-V2 `skillmimic/utils/motion_data_handler.py` (see
//! [`crate::motion::clip`]).

use super::columns::{bools, F32Rows};
use super::{f32_fixed, f32_list, schema_of, ColumnSpec};
use crate::motion::ClipFrames;
use anyhow::Result;
use arrow::array::{ArrayRef, BooleanArray, Float32Array, UInt32Array};
use arrow::datatypes::DataType;
use arrow::record_batch::RecordBatch;
use std::sync::Arc;

/// How many values a state column holds per frame.
#[derive(Clone, Copy, Debug)]
enum Width {
    /// This many (a `FixedSizeList` column).
    Fixed(usize),
    /// 3 per joint (a `List` column).
    Joints,
    /// 3 per body (a `List` column).
    Bodies,
    /// This many per object (a `List` column).
    PerObject(usize),
}

impl Width {
    /// Values per frame of `f`.
    fn of(self, f: &ClipFrames) -> usize {
        match self {
            Width::Fixed(n) => n,
            Width::Joints => f.n_joints * 3,
            Width::Bodies => f.n_bodies * 3,
            Width::PerObject(k) => k * f.n_objects,
        }
    }

    fn dtype(self) -> DataType {
        match self {
            Width::Fixed(n) => f32_fixed(n as i32),
            _ => f32_list(),
        }
    }

    fn rows(self) -> F32Rows {
        match self {
            Width::Fixed(n) => F32Rows::fixed(n),
            _ => F32Rows::list(),
        }
    }
}

/// A float state column: named after its field of [`ClipFrames`], with
/// its width per frame and meaning.
struct StateColumn {
    name: &'static str,
    width: Width,
    doc: &'static str,
    get: fn(&ClipFrames) -> &Vec<f32>,
    get_mut: fn(&mut ClipFrames) -> &mut Vec<f32>,
}

macro_rules! state_columns {
    ($($field:ident: $width:expr, $doc:expr;)*) => {
        [$(StateColumn {
            name: stringify!($field),
            width: $width,
            doc: $doc,
            get: |f| &f.$field,
            get_mut: |f| &mut f.$field,
        }),*]
    };
}

/// The float state columns, in table order (after `valid`).
#[rustfmt::skip]
const STATE_COLUMNS: [StateColumn; 14] = state_columns! {
    root_pos: Width::Fixed(3), "root (pelvis) world position, m; tensor cols 0:3";
    root_rot: Width::Fixed(4), "root world rotation, unit quaternion (x, y, z, w), sign-smoothed along the clip";
    root_rot_expmap: Width::Fixed(3), "root world rotation as stored, exp-map, rad; tensor cols 3:6";
    root_linvel: Width::Fixed(3), "root linear velocity, m/s: backward difference x fps, 0 at frame 0";
    root_angvel: Width::Fixed(3), "root angular velocity, rad/s: expmap(conj(q[i-1]) q[i]) x fps (body frame; metadata skillaug.angvel_frame)";
    joint_rot: Width::Joints, "[J*3] joint rotations, exp-map of each non-root body's local rotation, rad; tensor cols 9:9+3J";
    joint_vel: Width::Joints, "[J*3] joint exp-map velocities, rad/s: backward difference x fps";
    body_pos: Width::Bodies, "[B*3] body world positions in body order, m; tensor cols 165:324 (D337) or 189:372 (ParaHome)";
    body_vel: Width::Bodies, "[B*3] body linear velocities, m/s: backward difference x fps";
    obj_pos: Width::PerObject(3), "[O*3] object world positions, m";
    obj_rot: Width::PerObject(4), "[O*4] object rotations, unit quaternions (x, y, z, w), sign-smoothed";
    obj_rot_expmap: Width::PerObject(3), "[O*3] object rotation vectors, rad (BallPlay's stored negation undone)";
    obj_linvel: Width::PerObject(3), "[O*3] object linear velocities, m/s: backward difference x fps";
    obj_angvel: Width::PerObject(3), "[O*3] object angular velocities, rad/s (metadata skillaug.obj_angvel)";
};

/// The documented columns. J = joints, B = bodies (metadata
/// `skillaug.n_joints`, `skillaug.n_bodies`), O = objects of the clip
/// (`objects` in clips.parquet). Quaternions are (x, y, z, w).
pub fn columns() -> Vec<ColumnSpec> {
    use DataType::*;
    let mut cols = vec![
        ColumnSpec::new("clip_id", UInt32, false, "clip (clips.parquet clip_id)"),
        ColumnSpec::new(
            "frame",
            UInt32,
            false,
            "frame index within the clip, 0-based",
        ),
        ColumnSpec::new("time_s", Float32, false, "frame / fps, s"),
        ColumnSpec::new(
            "valid",
            Boolean,
            false,
            "false for a missing frame (all-zero row); its state columns are null",
        ),
    ];
    cols.extend(
        STATE_COLUMNS
            .iter()
            .map(|c| ColumnSpec::new(c.name, c.width.dtype(), true, c.doc)),
    );
    cols.push(ColumnSpec::new(
        "contact",
        Boolean,
        true,
        "reference ball/object contact flag: the last tensor column, rounded",
    ));
    cols
}

/// One clip's frames with its id and frame rate.
pub struct ClipInput<'a> {
    /// clip_id.
    pub clip_id: u32,
    /// Frame rate, Hz.
    pub fps: f64,
    /// The derived state.
    pub frames: &'a ClipFrames,
}

/// The record batch of every frame of `clips`, in order.
pub fn batch(clips: &[ClipInput<'_>]) -> Result<RecordBatch> {
    let n: usize = clips.iter().map(|c| c.frames.frames).sum();
    let mut clip_id = Vec::with_capacity(n);
    let mut frame = Vec::with_capacity(n);
    let mut time = Vec::with_capacity(n);
    let mut valid = Vec::with_capacity(n);
    let mut contact = Vec::with_capacity(n);
    let mut cols: Vec<F32Rows> = STATE_COLUMNS.iter().map(|c| c.width.rows()).collect();
    for c in clips {
        let f = c.frames;
        for i in 0..f.frames {
            clip_id.push(c.clip_id);
            frame.push(i as u32);
            time.push((i as f64 / c.fps) as f32);
            let ok = f.valid[i];
            valid.push(ok);
            contact.push(ok.then_some(f.contact[i]));
            for (col, sc) in cols.iter_mut().zip(&STATE_COLUMNS) {
                let (src, w) = ((sc.get)(f), sc.width.of(f));
                col.push(ok.then(|| &src[i * w..(i + 1) * w]));
            }
        }
    }
    let mut arrays: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(clip_id)),
        Arc::new(UInt32Array::from(frame)),
        Arc::new(Float32Array::from(time)),
        Arc::new(BooleanArray::from(valid)),
    ];
    arrays.extend(cols.into_iter().map(F32Rows::finish));
    arrays.push(bools(contact));
    Ok(RecordBatch::try_new(schema_of(&columns()), arrays)?)
}

/// Read `frames.parquet` back into one [`ClipFrames`] per clip of `clips`.
/// Rows must come clip by clip, frames in order (as `ingest` writes them).
pub fn read(path: &std::path::Path, clips: &[super::clips::ClipRow]) -> Result<Vec<ClipFrames>> {
    use super::read_util::{check_table, col, f32_row};
    use crate::motion::Skeleton;
    use anyhow::{anyhow, bail};
    use arrow::array::AsArray;
    use arrow::datatypes::UInt32Type;
    let t = super::io::read_parquet(path)?;
    check_table(&t, path, "frames")?;
    let mut out: Vec<ClipFrames> = clips
        .iter()
        .map(|c| {
            let sk = Skeleton::from_name(&c.skeleton).unwrap_or(Skeleton::MocapHumanoid);
            ClipFrames {
                frames: 0,
                n_joints: sk.n_joints(),
                n_bodies: sk.n_bodies(),
                n_objects: c.objects.len(),
                ..Default::default()
            }
        })
        .collect();
    for b in &t.batches {
        let ids = col(b, "clip_id", path)?
            .as_primitive::<UInt32Type>()
            .values()
            .to_vec();
        let frame = col(b, "frame", path)?
            .as_primitive::<UInt32Type>()
            .values()
            .to_vec();
        let valid = col(b, "valid", path)?.as_boolean().clone();
        let contact = col(b, "contact", path)?.as_boolean().clone();
        let arrays = STATE_COLUMNS
            .iter()
            .map(|sc| col(b, sc.name, path).cloned())
            .collect::<Result<Vec<_>>>()?;
        for r in 0..b.num_rows() {
            let c = out.get_mut(ids[r] as usize).ok_or_else(|| {
                anyhow!(
                    "{}: row {r}: clip_id {} not in clips.parquet",
                    path.display(),
                    ids[r]
                )
            })?;
            if frame[r] as usize != c.frames {
                bail!(
                    "{}: row {r}: frame {} of clip {} out of order",
                    path.display(),
                    frame[r],
                    ids[r]
                );
            }
            let ok = valid.value(r);
            for (sc, a) in STATE_COLUMNS.iter().zip(&arrays) {
                let (w, name) = (sc.width.of(c), sc.name);
                let dest = (sc.get_mut)(c);
                match f32_row(a, r) {
                    Some(v) if ok && v.len() == w => dest.extend_from_slice(&v),
                    None if !ok => dest.extend(std::iter::repeat_n(0.0, w)),
                    other => bail!(
                        "{}: row {r} (clip {}, frame {}): column `{name}` has {} values, expected {}",
                        path.display(), ids[r], frame[r], other.map_or(0, |v| v.len()), if ok { w } else { 0 }
                    ),
                }
            }
            c.valid.push(ok);
            c.contact.push(ok && contact.value(r));
            c.frames += 1;
        }
    }
    for (c, row) in out.iter().zip(clips) {
        if c.frames != row.frames as usize {
            bail!(
                "{}: clip {} has {} frames, clips.parquet says {}",
                path.display(),
                row.clip_id,
                c.frames,
                row.frames
            );
        }
    }
    Ok(out)
}
