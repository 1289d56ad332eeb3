//! Motion data: layouts, skeletons, quaternion maths and the per-frame state
//! derived from a clip tensor. Pure code, no I/O.

pub mod clip;
pub mod layout;
pub mod library;
pub mod quat;
pub mod state;

pub use clip::{ClipFrames, DeriveOptions};
pub use layout::{Layout, Skeleton};
pub use library::MotionLib;

/// Forward kinematics of a humanoid: the world body positions `[B*3]`, m,
/// of a posture (root position, m; root rotation, unit quaternion x, y, z,
/// w; joint exp-maps `[J*3]`, rad). What the augmentation code needs of a
/// humanoid model, given to it by its caller so that it depends on no model
/// format or physics engine (`sim::mjcf::Model` implements it).
pub trait Kinematics: Send + Sync {
    /// Body positions `[B*3]` of the posture.
    fn body_positions(&self, root_pos: [f32; 3], root_rot: [f32; 4], joint_rot: &[f32])
        -> Vec<f32>;
}
pub use state::State;
