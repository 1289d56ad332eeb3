//! One full simulation state in the layout of the ingested frames: the unit
//! that rewards compare, the augmentation stages perturb and stitch, and
//! (later) the simulator sets and reads.

use super::clip::ClipFrames;

/// Root, joint, body and object state of one frame. Quaternions are
/// (x, y, z, w); widths depend on the skeleton (J joints, B bodies) and the
/// number of objects O.
#[derive(Clone, Debug, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct State {
    /// Root world position, m.
    pub root_pos: [f32; 3],
    /// Root world rotation, unit quaternion.
    pub root_rot: [f32; 4],
    /// Root world rotation, exp-map, rad (what the SM reward compares).
    pub root_rot_expmap: [f32; 3],
    /// Root linear velocity, m/s.
    pub root_linvel: [f32; 3],
    /// Root angular velocity, rad/s.
    pub root_angvel: [f32; 3],
    /// `[J*3]` joint exp-maps, rad.
    pub joint_rot: Vec<f32>,
    /// `[J*3]` joint exp-map velocities, rad/s.
    pub joint_vel: Vec<f32>,
    /// `[B*3]` body world positions, m.
    pub body_pos: Vec<f32>,
    /// `[B*3]` body linear velocities, m/s.
    pub body_vel: Vec<f32>,
    /// `[O*3]` object positions, m.
    pub obj_pos: Vec<f32>,
    /// `[O*4]` object rotations, unit quaternions.
    pub obj_rot: Vec<f32>,
    /// `[O*3]` object linear velocities, m/s.
    pub obj_linvel: Vec<f32>,
    /// `[O*3]` object angular velocities, rad/s.
    pub obj_angvel: Vec<f32>,
    /// Reference contact flag (object touched).
    pub contact: bool,
}

fn arr<const N: usize>(v: &[f32], i: usize) -> [f32; N] {
    let mut a = [0f32; N];
    a.copy_from_slice(&v[i * N..(i + 1) * N]);
    a
}

fn row(v: &[f32], i: usize, w: usize) -> Vec<f32> {
    v[i * w..(i + 1) * w].to_vec()
}

impl ClipFrames {
    /// The state of frame `i` (`None` for a missing frame or out of range).
    pub fn state(&self, i: usize) -> Option<State> {
        if i >= self.frames || !self.valid[i] {
            return None;
        }
        let (j, b, o) = (self.n_joints * 3, self.n_bodies * 3, self.n_objects);
        Some(State {
            root_pos: arr(&self.root_pos, i),
            root_rot: arr(&self.root_rot, i),
            root_rot_expmap: arr(&self.root_rot_expmap, i),
            root_linvel: arr(&self.root_linvel, i),
            root_angvel: arr(&self.root_angvel, i),
            joint_rot: row(&self.joint_rot, i, j),
            joint_vel: row(&self.joint_vel, i, j),
            body_pos: row(&self.body_pos, i, b),
            body_vel: row(&self.body_vel, i, b),
            obj_pos: row(&self.obj_pos, i, 3 * o),
            obj_rot: row(&self.obj_rot, i, 4 * o),
            obj_linvel: row(&self.obj_linvel, i, 3 * o),
            obj_angvel: row(&self.obj_angvel, i, 3 * o),
            contact: self.contact[i],
        })
    }
}

/// The part of a state that fixes where everything is: what a viewer draws
/// and what a recorded rollout keeps per step.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Posture {
    /// Root world position, m.
    pub root_pos: [f32; 3],
    /// Root world rotation (x, y, z, w).
    pub root_rot: [f32; 4],
    /// `[J*3]` joint exp-maps, rad.
    pub joint_rot: Vec<f32>,
    /// `[O*3]` object positions, m.
    pub obj_pos: Vec<f32>,
    /// `[O*4]` object rotations (x, y, z, w).
    pub obj_rot: Vec<f32>,
}

impl State {
    /// This state's posture.
    pub fn posture(&self) -> Posture {
        Posture {
            root_pos: self.root_pos,
            root_rot: self.root_rot,
            joint_rot: self.joint_rot.clone(),
            obj_pos: self.obj_pos.clone(),
            obj_rot: self.obj_rot.clone(),
        }
    }
}
