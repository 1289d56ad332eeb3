//! Continuation past a clip's end: where a training reference resumes when it
//! reaches the last valid frame of its clip.
//!
//! For every clip `c` of skill A, the **seam** is the frame ŝ_j of A (any
//! clip of A, frames 2..F-2 as for starts) most similar to the clip's last
//! valid frame ŝ_L under S_k with the root's x, y and heading aligned (Eq. 19,
//! [`crate::reward::similarity`] with [`Align::default`]), the same rule the
//! STG applies across skills (paper Section 4.4). A loop must last: a frame of
//! `c` itself counts only when it lies at least `min_loop` frames before L,
//! and a frame of another clip only when `min_loop` frames follow it.
//!
//! The trainer ([`crate::rl::humanoid`]) continues an episode that reaches
//! ŝ_L with N = Eq. 20 (β) masked states and then ŝ_j, ŝ_{j+1}, ... (or
//! directly ŝ_{j+1} when N = 0, as for a start that is a reference frame),
//! every continued frame moved rigidly about the vertical so that ŝ_j's root
//! x, y and heading are where the simulated character's are at the seam.

use super::ats::start_frames;
use crate::motion::MotionLib;
use crate::reward::{self, Align, Weights};
use serde::{Deserialize, Serialize};

/// Where clip `clip`'s reference continues after its last valid frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Seam {
    /// The clip that ends.
    pub clip: u32,
    /// Its last valid frame L.
    pub last: u32,
    /// The clip the reference continues in.
    pub to_clip: u32,
    /// ŝ_j: the frame most similar to ŝ_L.
    pub to_frame: u32,
    /// β = S_k(ŝ_L, ŝ_j aligned), in (0, 1].
    pub beta: f64,
}

/// The seam of every clip (`None` for a clip without a valid frame or
/// without a candidate frame far enough from its end). `w`: the similarity
/// weights (the dataset's SM weights); `min_loop`: the shortest continued
/// segment, frames.
pub fn seams(lib: &MotionLib, w: &Weights, min_loop: usize) -> Vec<Option<Seam>> {
    (0..lib.clips.len())
        .map(|c| {
            let last = lib.frames[c].last_valid()?;
            let end = lib.state(c, last)?;
            let mut best: Option<Seam> = None;
            for c2 in lib.clips_of(&lib.clips[c].skill) {
                let Some(last2) = lib.frames[c2].last_valid() else {
                    continue;
                };
                let allowed = start_frames(&lib.frames[c2]);
                for (f, ok) in allowed.iter().enumerate() {
                    let far = if c2 == c {
                        f + min_loop <= last
                    } else {
                        f + min_loop <= last2
                    };
                    if !*ok || !far {
                        continue;
                    }
                    let Some(s) = lib.state(c2, f) else { continue };
                    let beta = reward::similarity(&end, &s, lib.skeleton, w, Align::default());
                    if best.is_none_or(|b| beta > b.beta) {
                        best = Some(Seam {
                            clip: c as u32,
                            last: last as u32,
                            to_clip: c2 as u32,
                            to_frame: f as u32,
                            beta,
                        });
                    }
                }
            }
            best
        })
        .collect()
}
