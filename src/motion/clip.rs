//! The per-frame state of one clip, derived from its `[frames, D]` tensor.
//!
//! Everything here follows the V2 BallPlay loader (Ingrid789/SkillMimic-V2
//! `skillmimic/utils/motion_data_handler.py`), applied to every layout:
//! * velocities are backward differences times the frame rate, zero at frame 0;
//! * if frame `i` or `i - 1` is missing, the velocity at `i` is copied from
//!   `i - 1` (applied in frame order, so a run of missing frames carries the
//!   last good velocity forward);
//! * the root quaternion is `quat_from_expmap(cols 3:6)`, sign-smoothed: it is
//!   negated whenever its dot product with the previous valid frame's is
//!   negative;
//! * the root angular velocity is `expmap(conj(q[i-1]) * q[i]) * fps`, a
//!   body-frame rate as in the reference loader (`angvel_frame = "body"`); the
//!   world-frame rate `expmap(q[i] * conj(q[i-1])) * fps` is an option;
//! * the object rotation is `quat_from_expmap(-cols)` for BallPlay (stored
//!   negated) and `quat_from_expmap(+cols)` for ParaHome.
//!
//! Where skillaug departs from the reference code, on purpose:
//! * The ParaHome reference loader differentiates the root rotation twice (a
//!   bug, `skillmimic/utils/paramotion_data_handler.py`); skillaug applies the
//!   BallPlay rule to every layout.
//! * The reference takes the object "angular velocity" as the backward
//!   difference of the rotation vectors, which is not an angular velocity;
//!   skillaug uses the quaternion rule of the root by default
//!   (`obj_angvel = "quat-diff"`) and offers the reference rule as
//!   `obj_angvel = "expmap-diff"`. Every shipped BallPlay ball rotation is the
//!   identity, so the two agree there.
//! * Object quaternions are sign-smoothed like the root's.
//!
//! A missing frame is a row whose D values are all exactly zero
//! (`motion_data_handler.py`, paper Eq. 5); its state is kept out of the
//! tables (null).

use super::layout::Layout;
use super::quat::{self, Quat, Vec3};
use serde::{Deserialize, Serialize};

/// The frame in which root and object angular velocities are expressed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum AngvelFrame {
    /// `expmap(conj(q[i-1]) q[i]) fps`: the reference loader's rule
    /// (Ingrid789/SkillMimic-V2 `skillmimic/utils/motion_data_handler.py`).
    #[default]
    Body,
    /// `expmap(q[i] conj(q[i-1])) fps`: the world-frame angular velocity.
    World,
}

/// How the object angular velocity is derived.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum ObjAngvel {
    /// From consecutive quaternions, like the root (a true angular velocity).
    #[default]
    QuatDiff,
    /// Backward difference of rotation vectors, as the reference code does.
    ExpmapDiff,
}

/// Settings of the derivation.
#[derive(Clone, Copy, Debug)]
pub struct DeriveOptions {
    /// Frame rate used for finite differences, Hz.
    pub fps: f64,
    /// Frame of the angular velocities.
    pub angvel_frame: AngvelFrame,
    /// Rule for object angular velocities.
    pub obj_angvel: ObjAngvel,
    /// How many of the layout's objects to keep (0 drops the Locomotion dummy ball).
    pub n_objects: usize,
}

/// A problem with a clip tensor's values.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DeriveError {
    /// A NaN or infinite value.
    #[error("non-finite value {value} at frame {frame}, column {column} ({field})")]
    NonFinite {
        /// Frame (row) index.
        frame: usize,
        /// Column index.
        column: usize,
        /// What the column holds.
        field: String,
        /// The value.
        value: f32,
    },
    /// The tensor has a different width than the layout.
    #[error("{got} columns, expected {expected} for layout {layout}")]
    Columns {
        /// Columns found.
        got: usize,
        /// Columns of the layout.
        expected: usize,
        /// The layout.
        layout: Layout,
    },
    /// More objects requested than the layout stores.
    #[error("{requested} objects requested but layout {layout} stores {stored}")]
    Objects {
        /// Requested count.
        requested: usize,
        /// Stored count.
        stored: usize,
        /// The layout.
        layout: Layout,
    },
    /// A clip with no frames.
    #[error("the clip has no frames")]
    Empty,
}

/// Per-frame state of one clip, flattened frame-major. Entries of missing
/// frames hold zeros and are written as nulls.
#[derive(Clone, Debug, Default)]
pub struct ClipFrames {
    /// Number of frames F.
    pub frames: usize,
    /// Joints J (52 or 60).
    pub n_joints: usize,
    /// Bodies B (53 or 61).
    pub n_bodies: usize,
    /// Objects kept.
    pub n_objects: usize,
    /// `[F]` false for a missing (all-zero) frame.
    pub valid: Vec<bool>,
    /// `[F, 3]` root world position, m (cols 0:3).
    pub root_pos: Vec<f32>,
    /// `[F, 4]` root rotation, unit quaternion (x, y, z, w), sign-smoothed.
    pub root_rot: Vec<f32>,
    /// `[F, 3]` root rotation as stored, exp-map, rad (cols 3:6).
    pub root_rot_expmap: Vec<f32>,
    /// `[F, 3]` root linear velocity, m/s.
    pub root_linvel: Vec<f32>,
    /// `[F, 3]` root angular velocity, rad/s.
    pub root_angvel: Vec<f32>,
    /// `[F, J*3]` joint rotations, exp-maps, rad (cols 9:9+3J).
    pub joint_rot: Vec<f32>,
    /// `[F, J*3]` joint exp-map velocities, rad/s.
    pub joint_vel: Vec<f32>,
    /// `[F, B*3]` body world positions, m.
    pub body_pos: Vec<f32>,
    /// `[F, B*3]` body linear velocities, m/s.
    pub body_vel: Vec<f32>,
    /// `[F, O*3]` object world positions, m.
    pub obj_pos: Vec<f32>,
    /// `[F, O*4]` object rotations, unit quaternions (x, y, z, w).
    pub obj_rot: Vec<f32>,
    /// `[F, O*3]` object rotation vectors, rad (BallPlay's stored negation undone).
    pub obj_rot_expmap: Vec<f32>,
    /// `[F, O*3]` object linear velocities, m/s.
    pub obj_linvel: Vec<f32>,
    /// `[F, O*3]` object angular velocities, rad/s.
    pub obj_angvel: Vec<f32>,
    /// `[F]` contact flag (the last column, rounded).
    pub contact: Vec<bool>,
}

impl ClipFrames {
    /// Keep the first `n` frames (no change when the clip has at most `n`).
    pub fn truncate(&mut self, n: usize) {
        if n >= self.frames {
            return;
        }
        let f = self.frames;
        let cut = |v: &mut Vec<f32>| {
            let width = v.len() / f;
            v.truncate(n * width);
        };
        for v in [
            &mut self.root_pos,
            &mut self.root_rot,
            &mut self.root_rot_expmap,
            &mut self.root_linvel,
            &mut self.root_angvel,
            &mut self.joint_rot,
            &mut self.joint_vel,
            &mut self.body_pos,
            &mut self.body_vel,
            &mut self.obj_pos,
            &mut self.obj_rot,
            &mut self.obj_rot_expmap,
            &mut self.obj_linvel,
            &mut self.obj_angvel,
        ] {
            cut(v);
        }
        self.valid.truncate(n);
        self.contact.truncate(n);
        self.frames = n;
    }

    /// The last valid frame (`None` when no frame is valid).
    pub fn last_valid(&self) -> Option<usize> {
        (0..self.frames).rev().find(|f| self.valid[*f])
    }

    /// Number of valid frames.
    pub fn valid_frames(&self) -> usize {
        self.valid.iter().filter(|v| **v).count()
    }
}

/// True when a row is the missing-frame marker (all values exactly zero).
pub fn is_missing(row: &[f32]) -> bool {
    row.iter().all(|v| *v == 0.0)
}

/// Derive the per-frame state of a row-major `[frames, layout.columns()]`
/// tensor.
pub fn derive(
    data: &[f32],
    layout: Layout,
    opts: &DeriveOptions,
) -> Result<ClipFrames, DeriveError> {
    let d = layout.columns();
    if !data.len().is_multiple_of(d) {
        return Err(DeriveError::Columns {
            got: data.len(),
            expected: d,
            layout,
        });
    }
    let f = data.len() / d;
    if f == 0 {
        return Err(DeriveError::Empty);
    }
    let stored = layout.objects().len();
    if opts.n_objects > stored {
        return Err(DeriveError::Objects {
            requested: opts.n_objects,
            stored,
            layout,
        });
    }
    if let Some(i) = data.iter().position(|v| !v.is_finite()) {
        return Err(DeriveError::NonFinite {
            frame: i / d,
            column: i % d,
            field: layout.field_of(i % d),
            value: data[i],
        });
    }
    let rows: Vec<&[f32]> = data.chunks_exact(d).collect();
    let valid: Vec<bool> = rows.iter().map(|r| !is_missing(r)).collect();
    let sk = layout.skeleton();
    let (nj, nb, no) = (sk.n_joints(), sk.n_bodies(), opts.n_objects);
    let fps = opts.fps;

    let slice = |start: usize, width: usize| -> Vec<f32> {
        rows.iter()
            .flat_map(|r| r[start..start + width].iter().copied())
            .collect()
    };
    let root_pos = slice(0, 3);
    let root_rot_expmap = slice(3, 3);
    let joint_rot = slice(Layout::JOINTS, 3 * nj);
    let body_pos = slice(layout.body_pos(), 3 * nb);

    let root_q = smoothed_quats(&rows, &valid, |r| expmap_at(r, 3, false));
    let root_rot = root_q.iter().flat_map(|q| q.map(|v| v as f32)).collect();
    let root_angvel = angvel(&root_q, &valid, fps, opts.angvel_frame);

    let mut obj_pos = Vec::with_capacity(f * 3 * no);
    let mut obj_rot = vec![0f32; f * 4 * no];
    let mut obj_rot_expmap = vec![0f32; f * 3 * no];
    let mut obj_angvel = vec![0f32; f * 3 * no];
    for r in &rows {
        for o in &layout.objects()[..no] {
            obj_pos.extend_from_slice(&r[o.pos..o.pos + 3]);
        }
    }
    let neg = layout.object_rotation_negated();
    for (k, o) in layout.objects()[..no].iter().enumerate() {
        let e: Vec<Vec3> = rows.iter().map(|r| expmap_at(r, o.rot, neg)).collect();
        let q = smoothed_quats(&rows, &valid, |r| expmap_at(r, o.rot, neg));
        let w = match opts.obj_angvel {
            ObjAngvel::QuatDiff => angvel(&q, &valid, fps, opts.angvel_frame),
            ObjAngvel::ExpmapDiff => {
                let flat: Vec<f32> = e.iter().flat_map(|v| v.map(|x| x as f32)).collect();
                backward_diff(&flat, 3, &valid, fps)
            }
        };
        for i in 0..f {
            for c in 0..4 {
                obj_rot[(i * no + k) * 4 + c] = q[i][c] as f32;
            }
            for c in 0..3 {
                // -0.0 for a stored +0.0 would make the negation visible in
                // bit-exact comparisons for no benefit: store +0.0.
                obj_rot_expmap[(i * no + k) * 3 + c] = (e[i][c] as f32) + 0.0;
                obj_angvel[(i * no + k) * 3 + c] = w[i * 3 + c];
            }
        }
    }

    Ok(ClipFrames {
        frames: f,
        n_joints: nj,
        n_bodies: nb,
        n_objects: no,
        root_linvel: backward_diff(&root_pos, 3, &valid, fps),
        root_angvel,
        joint_vel: backward_diff(&joint_rot, 3 * nj, &valid, fps),
        body_vel: backward_diff(&body_pos, 3 * nb, &valid, fps),
        obj_linvel: backward_diff(&obj_pos, 3 * no, &valid, fps),
        contact: rows.iter().map(|r| r[layout.contact()] > 0.5).collect(),
        valid,
        root_pos,
        root_rot,
        root_rot_expmap,
        joint_rot,
        body_pos,
        obj_pos,
        obj_rot,
        obj_rot_expmap,
        obj_angvel,
    })
}

fn expmap_at(row: &[f32], col: usize, negate: bool) -> Vec3 {
    let s = if negate { -1.0 } else { 1.0 };
    [
        s * row[col] as f64,
        s * row[col + 1] as f64,
        s * row[col + 2] as f64,
    ]
}

/// Quaternions of each frame, sign-smoothed against the previous valid frame.
fn smoothed_quats(rows: &[&[f32]], valid: &[bool], e: impl Fn(&[f32]) -> Vec3) -> Vec<Quat> {
    let mut prev: Option<Quat> = None;
    rows.iter()
        .zip(valid)
        .map(|(r, &ok)| {
            if !ok {
                return quat::IDENTITY;
            }
            let mut q = quat::from_expmap(e(r));
            if let Some(p) = prev {
                q = quat::sign_like(q, p);
            }
            prev = Some(q);
            q
        })
        .collect()
}

/// Backward difference times `fps` of a `[F, width]` array with the
/// missing-frame copy rule of the reference loader (Ingrid789/SkillMimic-V2
/// `skillmimic/utils/motion_data_handler.py`, `_compute_velocity`).
pub fn backward_diff(x: &[f32], width: usize, valid: &[bool], fps: f64) -> Vec<f32> {
    let f = valid.len();
    let mut v = vec![0f32; f * width];
    for i in 1..f {
        let (done, rest) = v.split_at_mut(i * width);
        let out = &mut rest[..width];
        if valid[i] && valid[i - 1] {
            for c in 0..width {
                let d = x[i * width + c] as f64 - x[(i - 1) * width + c] as f64;
                out[c] = (d * fps) as f32;
            }
        } else {
            out.copy_from_slice(&done[(i - 1) * width..]);
        }
    }
    v
}

/// Angular velocity from consecutive quaternions, with the same missing-frame
/// rule as [`backward_diff`].
fn angvel(q: &[Quat], valid: &[bool], fps: f64, frame: AngvelFrame) -> Vec<f32> {
    let f = q.len();
    let mut w = vec![0f32; f * 3];
    for i in 1..f {
        if valid[i] && valid[i - 1] {
            let rel = match frame {
                AngvelFrame::Body => quat::mul(quat::conj(q[i - 1]), q[i]),
                AngvelFrame::World => quat::mul(q[i], quat::conj(q[i - 1])),
            };
            let e = quat::to_expmap(rel);
            for c in 0..3 {
                w[i * 3 + c] = (e[c] * fps) as f32;
            }
        } else {
            let (done, rest) = w.split_at_mut(i * 3);
            rest[..3].copy_from_slice(&done[(i - 1) * 3..]);
        }
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts(n_objects: usize) -> DeriveOptions {
        DeriveOptions {
            fps: 60.0,
            angvel_frame: AngvelFrame::Body,
            obj_angvel: ObjAngvel::QuatDiff,
            n_objects,
        }
    }

    /// A smooth synthetic BallPlay clip: every column a different sine.
    fn synthetic(frames: usize) -> Vec<f32> {
        let d = 337;
        (0..frames * d)
            .map(|k| {
                let (i, c) = (k / d, k % d);
                (0.3 * ((c as f32) * 0.7 + (i as f32) * 0.05).sin()) + 0.01
            })
            .collect()
    }

    #[test]
    fn missing_frames_copy_the_previous_velocity() {
        let mut x = synthetic(8);
        for v in &mut x[3 * 337..4 * 337] {
            *v = 0.0;
        }
        for v in &mut x[4 * 337..5 * 337] {
            *v = 0.0;
        }
        let c = derive(&x, Layout::BallPlay337, &opts(1)).unwrap();
        assert_eq!(c.valid, [true, true, true, false, false, true, true, true]);
        let v = |i: usize| &c.root_linvel[i * 3..i * 3 + 3];
        assert_eq!(v(0), [0.0; 3]);
        let expect2: Vec<f32> = (0..3)
            .map(|k| ((x[2 * 337 + k] as f64 - x[337 + k] as f64) * 60.0) as f32)
            .collect();
        assert_eq!(v(2), &expect2[..]);
        // frames 3, 4 (missing) and 5 (after a missing one) carry frame 2's velocity
        assert_eq!(v(3), v(2));
        assert_eq!(v(4), v(2));
        assert_eq!(v(5), v(2));
        assert_ne!(v(6), v(2));
        assert_eq!(&c.root_angvel[15..18], &c.root_angvel[6..9]);
        assert_eq!(c.valid_frames(), 6);
    }

    #[test]
    fn a_missing_first_frame_keeps_zero_velocity() {
        let mut x = synthetic(3);
        for v in &mut x[..337] {
            *v = 0.0;
        }
        let c = derive(&x, Layout::BallPlay337, &opts(1)).unwrap();
        assert_eq!(&c.root_linvel[..6], &[0.0; 6]);
        assert_ne!(&c.root_linvel[6..9], &[0.0; 3]);
    }

    #[test]
    fn quaternions_are_sign_smoothed_unit_quaternions() {
        // A root turning steadily about z through +-pi, where exp-maps flip.
        let f = 40;
        let mut x = synthetic(f);
        for i in 0..f {
            let a = 2.6 + 0.03 * i as f32;
            let wrapped = if a > std::f32::consts::PI {
                a - 2.0 * std::f32::consts::PI
            } else {
                a
            };
            x[i * 337 + 3..i * 337 + 6].copy_from_slice(&[0.0, 0.0, wrapped]);
        }
        let c = derive(&x, Layout::BallPlay337, &opts(1)).unwrap();
        for i in 0..f {
            let q = &c.root_rot[i * 4..i * 4 + 4];
            let n: f32 = q.iter().map(|v| v * v).sum();
            assert!((n - 1.0).abs() < 1e-6);
            if i > 0 {
                let p = &c.root_rot[(i - 1) * 4..i * 4];
                let d: f32 = p.iter().zip(q).map(|(a, b)| a * b).sum();
                assert!(d > 0.0, "sign flip at frame {i}");
                // 0.03 rad per frame about +z at 60 fps
                let w = &c.root_angvel[i * 3..i * 3 + 3];
                assert!((w[2] - 1.8).abs() < 1e-3 && w[0].abs() < 1e-4, "{w:?}");
            }
        }
    }

    #[test]
    fn ballplay_object_rotation_negation_is_undone() {
        let mut x = synthetic(2);
        x[327..330].copy_from_slice(&[0.1, -0.2, 0.3]);
        let c = derive(&x, Layout::BallPlay337, &opts(1)).unwrap();
        assert_eq!(&c.obj_rot_expmap[..3], &[-0.1, 0.2, -0.3]);
        let zero = derive(&x, Layout::BallPlay337, &opts(0)).unwrap();
        assert!(zero.obj_pos.is_empty() && zero.obj_rot.is_empty());
    }

    #[test]
    fn non_finite_values_name_the_frame_and_field() {
        let mut x = synthetic(3);
        x[2 * 337 + 12] = f32::NAN;
        let e = derive(&x, Layout::BallPlay337, &opts(1)).unwrap_err();
        assert!(
            matches!(
                e,
                DeriveError::NonFinite {
                    frame: 2,
                    column: 12,
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("joint 1 (L_Knee)"), "{e}");
    }

    #[test]
    fn wrong_width_and_empty_are_errors() {
        assert!(matches!(
            derive(&[0.0; 10], Layout::BallPlay337, &opts(1)),
            Err(DeriveError::Columns { .. })
        ));
        assert!(matches!(
            derive(&[], Layout::BallPlay337, &opts(1)),
            Err(DeriveError::Empty)
        ));
        assert!(matches!(
            derive(&synthetic(1), Layout::BallPlay337, &opts(2)),
            Err(DeriveError::Objects { .. })
        ));
    }
}
