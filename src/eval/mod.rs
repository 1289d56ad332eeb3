//! Evaluation: success rules ([`rules`]) and the trial runner of
//! `skillaug eval`.

pub mod rules;
