//! State Transition Field sampling (being written).
