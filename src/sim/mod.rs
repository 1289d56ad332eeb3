//! The simulated humanoid: the MJCF model ([`mjcf`]), one rapier3d world
//! ([`world`]), its objects ([`objects`]) and a vectorised environment of
//! independent worlds stepped in parallel ([`vec_env`]), with accuracy
//! ([`checks`]) and speed ([`mod@bench`]) measurements.

pub mod ball_path;
pub mod bench;
pub mod checks;
pub mod hand_path;
pub mod mjcf;
pub mod objects;
pub mod push;
pub mod rot;
pub mod vec_env;
pub mod world;

pub use objects::ObjectSpec;
pub use world::{ContactReport, SimOptions, World};
