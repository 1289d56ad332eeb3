//! Adaptive Trajectory Sampling (being written).
