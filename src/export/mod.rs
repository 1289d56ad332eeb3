//! Motion and policies out of skillaug: the motions a run folder holds
//! ([`motions`], shared with the viewer), as BVH ([`bvh`]) and glTF binary
//! ([`gltf`]) files, and a trained policy as an ONNX model ([`onnx`]).

pub mod bvh;
pub mod gltf;
pub mod motions;
pub mod onnx;
