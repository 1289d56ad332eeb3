//! The simulated humanoid. So far: the MJCF model ([`mjcf`]); the rapier3d
//! world comes with the simulation issue.

pub mod mjcf;
