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

/// The documented columns. J = joints, B = bodies (metadata
/// `skillaug.n_joints`, `skillaug.n_bodies`), O = objects of the clip
/// (`objects` in clips.parquet). Quaternions are (x, y, z, w).
pub fn columns() -> Vec<ColumnSpec> {
    use DataType::*;
    vec![
        ColumnSpec::new("clip_id", UInt32, false, "clip (clips.parquet clip_id)"),
        ColumnSpec::new("frame", UInt32, false, "frame index within the clip, 0-based"),
        ColumnSpec::new("time_s", Float32, false, "frame / fps, s"),
        ColumnSpec::new("valid", Boolean, false, "false for a missing frame (all-zero row); its state columns are null"),
        ColumnSpec::new("root_pos", f32_fixed(3), true, "root (pelvis) world position, m; tensor cols 0:3"),
        ColumnSpec::new("root_rot", f32_fixed(4), true, "root world rotation, unit quaternion (x, y, z, w), sign-smoothed along the clip"),
        ColumnSpec::new("root_rot_expmap", f32_fixed(3), true, "root world rotation as stored, exp-map, rad; tensor cols 3:6"),
        ColumnSpec::new("root_linvel", f32_fixed(3), true, "root linear velocity, m/s: backward difference x fps, 0 at frame 0"),
        ColumnSpec::new("root_angvel", f32_fixed(3), true, "root angular velocity, rad/s: expmap(conj(q[i-1]) q[i]) x fps (body frame; metadata skillaug.angvel_frame)"),
        ColumnSpec::new("joint_rot", f32_list(), true, "[J*3] joint rotations, exp-map of each non-root body's local rotation, rad; tensor cols 9:9+3J"),
        ColumnSpec::new("joint_vel", f32_list(), true, "[J*3] joint exp-map velocities, rad/s: backward difference x fps"),
        ColumnSpec::new("body_pos", f32_list(), true, "[B*3] body world positions in body order, m; tensor cols 165:324 (D337) or 189:372 (ParaHome)"),
        ColumnSpec::new("body_vel", f32_list(), true, "[B*3] body linear velocities, m/s: backward difference x fps"),
        ColumnSpec::new("obj_pos", f32_list(), true, "[O*3] object world positions, m"),
        ColumnSpec::new("obj_rot", f32_list(), true, "[O*4] object rotations, unit quaternions (x, y, z, w), sign-smoothed"),
        ColumnSpec::new("obj_rot_expmap", f32_list(), true, "[O*3] object rotation vectors, rad (BallPlay's stored negation undone)"),
        ColumnSpec::new("obj_linvel", f32_list(), true, "[O*3] object linear velocities, m/s: backward difference x fps"),
        ColumnSpec::new("obj_angvel", f32_list(), true, "[O*3] object angular velocities, rad/s (metadata skillaug.obj_angvel)"),
        ColumnSpec::new("contact", Boolean, true, "reference ball/object contact flag: the last tensor column, rounded"),
    ]
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
    let mut cols: Vec<F32Rows> = vec![
        F32Rows::fixed(3),
        F32Rows::fixed(4),
        F32Rows::fixed(3),
        F32Rows::fixed(3),
        F32Rows::fixed(3),
    ];
    cols.extend((0..9).map(|_| F32Rows::list()));
    for c in clips {
        let f = c.frames;
        let (j, b, o) = (f.n_joints * 3, f.n_bodies * 3, f.n_objects);
        for i in 0..f.frames {
            clip_id.push(c.clip_id);
            frame.push(i as u32);
            time.push((i as f64 / c.fps) as f32);
            let ok = f.valid[i];
            valid.push(ok);
            contact.push(ok.then_some(f.contact[i]));
            let parts: [(&Vec<f32>, usize); 14] = [
                (&f.root_pos, 3),
                (&f.root_rot, 4),
                (&f.root_rot_expmap, 3),
                (&f.root_linvel, 3),
                (&f.root_angvel, 3),
                (&f.joint_rot, j),
                (&f.joint_vel, j),
                (&f.body_pos, b),
                (&f.body_vel, b),
                (&f.obj_pos, 3 * o),
                (&f.obj_rot, 4 * o),
                (&f.obj_rot_expmap, 3 * o),
                (&f.obj_linvel, 3 * o),
                (&f.obj_angvel, 3 * o),
            ];
            for (col, (src, w)) in cols.iter_mut().zip(parts) {
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
    const NAMES: [&str; 14] = [
        "root_pos",
        "root_rot",
        "root_rot_expmap",
        "root_linvel",
        "root_angvel",
        "joint_rot",
        "joint_vel",
        "body_pos",
        "body_vel",
        "obj_pos",
        "obj_rot",
        "obj_rot_expmap",
        "obj_linvel",
        "obj_angvel",
    ];
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
        let arrays = NAMES
            .iter()
            .map(|n| col(b, n, path).cloned())
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
            let (j, bd, o) = (c.n_joints * 3, c.n_bodies * 3, c.n_objects);
            let widths = [
                3,
                4,
                3,
                3,
                3,
                j,
                j,
                bd,
                bd,
                3 * o,
                4 * o,
                3 * o,
                3 * o,
                3 * o,
            ];
            let dests: [&mut Vec<f32>; 14] = [
                &mut c.root_pos,
                &mut c.root_rot,
                &mut c.root_rot_expmap,
                &mut c.root_linvel,
                &mut c.root_angvel,
                &mut c.joint_rot,
                &mut c.joint_vel,
                &mut c.body_pos,
                &mut c.body_vel,
                &mut c.obj_pos,
                &mut c.obj_rot,
                &mut c.obj_rot_expmap,
                &mut c.obj_linvel,
                &mut c.obj_angvel,
            ];
            for ((dest, a), (w, name)) in
                dests.into_iter().zip(&arrays).zip(widths.iter().zip(NAMES))
            {
                match f32_row(a, r) {
                    Some(v) if ok && v.len() == *w => dest.extend_from_slice(&v),
                    None if !ok => dest.extend(std::iter::repeat_n(0.0, *w)),
                    other => bail!(
                        "{}: row {r} (clip {}, frame {}): column `{name}` has {} values, expected {}",
                        path.display(), ids[r], frame[r], other.map_or(0, |v| v.len()), if ok { *w } else { 0 }
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
