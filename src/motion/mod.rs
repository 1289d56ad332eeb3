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
pub use state::State;
