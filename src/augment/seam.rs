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
use crate::motion::{quat, MotionLib, State};
use crate::reward::{self, Align, Weights};
use serde::{Deserialize, Serialize};

/// What a continued reference's seam frame is matched to when a clip
/// ends (`train.seam_match`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SeamMatch {
    /// The clip's last valid frame: one seam per clip, found once
    /// ([`seams`]), as the STG links reference frames (paper Section 4.4).
    #[default]
    Reference,
    /// The simulated state when the clip ends: the skill's frame most
    /// similar to where the character and the ball are then
    /// ([`SeamPool::nearest`]), so a dribble whose ball runs low or early
    /// continues at the reference's phase that has the ball there, after
    /// the masked steps Eq. 20 gives for that similarity; a state no frame
    /// is more similar to than tau continues at the clip's own seam. Not
    /// in the paper or the reference code.
    Simulation,
}

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
    let pool = SeamPool::new(lib, min_loop);
    (0..lib.clips.len())
        .map(|c| {
            let last = lib.frames[c].last_valid()?;
            pool.nearest(lib, c, &lib.state(c, last)?, w)
        })
        .collect()
}

/// The frames a reference may continue at after a clip's end, per skill:
/// every frame f of every clip of the skill that a start may be
/// ([`start_frames`]) and that leaves at least `min_loop` frames before its
/// clip's last valid frame (a frame of the ending clip itself then lies at
/// least `min_loop` frames before L, as [`seams`] requires), with its
/// state, in clip then frame order.
#[derive(Clone, Debug, Default)]
pub struct SeamPool {
    /// Per clip: index into `skills` of its skill's candidates.
    skill_of: Vec<usize>,
    /// Per skill: (clip, frame, reference state) of each candidate.
    skills: Vec<Vec<(u32, u32, State)>>,
}

impl SeamPool {
    /// The candidates of every skill of `lib` (`min_loop`: frames).
    pub fn new(lib: &MotionLib, min_loop: usize) -> SeamPool {
        let mut names: Vec<&str> = Vec::new();
        let mut pool = SeamPool::default();
        for row in &lib.clips {
            let k = match names.iter().position(|n| *n == row.skill) {
                Some(k) => k,
                None => {
                    names.push(&row.skill);
                    let mut cands = Vec::new();
                    for c2 in lib.clips_of(&row.skill) {
                        let Some(last2) = lib.frames[c2].last_valid() else {
                            continue;
                        };
                        for (f, ok) in start_frames(&lib.frames[c2]).iter().enumerate() {
                            if *ok && f + min_loop <= last2 {
                                if let Some(s) = lib.state(c2, f) {
                                    cands.push((c2 as u32, f as u32, s));
                                }
                            }
                        }
                    }
                    pool.skills.push(cands);
                    names.len() - 1
                }
            };
            pool.skill_of.push(k);
        }
        pool
    }

    /// The seam of clip `clip` continued from state `end`: the candidate of
    /// its skill most similar to `end` under S_k (Eq. 19, `w`) with the
    /// root's x, y and heading aligned (the first such frame on a tie;
    /// `None` for a clip without a valid frame or a skill without
    /// candidates). `end` is the clip's last valid frame for [`seams`], or
    /// the simulated state when the trainer matches seams to the
    /// simulation (`train.seam_match = "simulation"`).
    pub fn nearest(&self, lib: &MotionLib, clip: usize, end: &State, w: &Weights) -> Option<Seam> {
        let last = lib.frames.get(clip)?.last_valid()?;
        let mut best: Option<Seam> = None;
        for (c2, f, s) in &self.skills[*self.skill_of.get(clip)?] {
            let beta = reward::similarity(end, s, lib.skeleton, w, Align::default());
            if best.is_none_or(|b| beta > b.beta) {
                best = Some(Seam {
                    clip: clip as u32,
                    last: last as u32,
                    to_clip: *c2,
                    to_frame: *f,
                    beta,
                });
            }
        }
        best
    }
}

/// For every clip, the frame L' at which training leaves it: among the
/// valid frames of its last `search` frames (the last frame included),
/// the one whose seam is most similar (the best S_k over the skill's
/// frames, aligned as in [`seams`], a frame of the clip itself at least
/// `min_loop` frames before L', a frame of another clip at least
/// `min_loop` frames before the earliest frame that clip may be cut at, so
/// that [`seams`] of the cut clips finds a seam at least as similar); the
/// last valid frame where no frame does better or `search` is 0. Cutting a
/// clip at L' makes a loop of a periodic motion (a dribble) close where its
/// phases match instead of wherever the capture stopped.
pub fn leave_frames(lib: &MotionLib, w: &Weights, min_loop: usize, search: usize) -> Vec<usize> {
    (0..lib.clips.len())
        .map(|c| {
            let Some(last) = lib.frames[c].last_valid() else {
                return 0;
            };
            // the skill's candidate frames, built once for every leave
            // frame: (clip, frame, state)
            let mut candidates = Vec::new();
            for c2 in lib.clips_of(&lib.clips[c].skill) {
                let Some(last2) = lib.frames[c2].last_valid() else {
                    continue;
                };
                // another clip may be cut too: only its frames that every
                // cut keeps count, so the seam found here stays
                let bound = if c2 == c {
                    last
                } else {
                    last2.saturating_sub(search)
                };
                for (f, ok) in start_frames(&lib.frames[c2]).iter().enumerate() {
                    if *ok && f + min_loop <= bound {
                        if let Some(s) = lib.state(c2, f) {
                            candidates.push((c2, f, s));
                        }
                    }
                }
            }
            let mut best = (last, f64::NEG_INFINITY);
            for leave in (last.saturating_sub(search)..=last).rev() {
                let Some(end) = lib.state(c, leave) else {
                    continue;
                };
                let top = candidates
                    .iter()
                    .filter(|(c2, f, _)| *c2 != c || f + min_loop <= leave)
                    .map(|(_, _, s)| reward::similarity(&end, s, lib.skeleton, w, Align::default()))
                    .fold(f64::NEG_INFINITY, f64::max);
                if top > best.1 {
                    best = (leave, top);
                }
            }
            best.0
        })
        .collect()
}

/// A shortest loop of `min_loop_s` seconds at `fps` frames per second, in
/// frames (at least one).
pub fn min_loop_frames(min_loop_s: f64, fps: f64) -> usize {
    ((min_loop_s * fps).ceil() as usize).max(1)
}

/// Cut each clip of `clips` after the frame at which training leaves it
/// ([`leave_frames`] with the library's SM weights over the last
/// `search_s` seconds at `fps`; a shortest loop of `min_loop_s` seconds):
/// its later frames are dropped, its row's frame counts follow.
pub fn cut_at_leave_frames(
    lib: &mut MotionLib,
    clips: &[usize],
    min_loop_s: f64,
    search_s: f64,
    fps: f64,
) {
    let w = Weights::sm(reward::DatasetKind::of_library(lib));
    let search = (search_s * fps).round() as usize;
    let leave = leave_frames(lib, &w, min_loop_frames(min_loop_s, fps), search);
    for &c in clips {
        let f = &mut lib.frames[c];
        f.truncate(leave[c] + 1);
        lib.clips[c].frames = f.frames as u32;
        lib.clips[c].valid_frames = f.valid_frames() as u32;
    }
}

/// The seams training uses: [`seams`] with the library's SM weights (the
/// dataset's, [`Weights::sm`]) and a shortest loop of `min_loop_s` seconds
/// at `fps` frames per second ([`min_loop_frames`]). Returns the seams and
/// that loop length in frames.
pub fn training_seams(lib: &MotionLib, min_loop_s: f64, fps: f64) -> (Vec<Option<Seam>>, usize) {
    let min_loop = min_loop_frames(min_loop_s, fps);
    let w = Weights::sm(reward::DatasetKind::of_library(lib));
    (seams(lib, &w, min_loop), min_loop)
}

/// A reference frame blended across a seam: `from` (the frame the old clip
/// ended on) moved so its root x, y and heading are `to`'s
/// ([`reward::align_to`]), then mixed with `to` (a frame after the seam)
/// with weight `w` on `to`: heights, body and object positions,
/// velocities and joint exp-maps linearly, root and object rotations by
/// normalised linear interpolation of the quaternions (signs matched);
/// contact flag from `to`. Blending the first K frames after a seam with
/// weights 1/(K+1), ..., K/(K+1) turns the jump to a dissimilar seam frame
/// into a transition over K steps. Unlike a motion graph's transition
/// (Kovar et al. 2002, Section 3.2, where both motions keep advancing over
/// the window) the old clip has no frames left here, so its last frame is
/// held, only moved onto each new root.
pub fn blend(from: &State, to: &State, w: f32) -> State {
    let a = reward::align_to(to, from, Align::default());
    let mut o = to.clone();
    let mix = |x: &mut [f32], y: &[f32]| {
        for (o, a) in x.iter_mut().zip(y) {
            *o = a + w * (*o - a);
        }
    };
    mix(&mut o.root_pos, &a.root_pos);
    mix(&mut o.root_linvel, &a.root_linvel);
    mix(&mut o.root_angvel, &a.root_angvel);
    mix(&mut o.joint_rot, &a.joint_rot);
    mix(&mut o.joint_vel, &a.joint_vel);
    mix(&mut o.body_pos, &a.body_pos);
    mix(&mut o.body_vel, &a.body_vel);
    mix(&mut o.obj_pos, &a.obj_pos);
    mix(&mut o.obj_linvel, &a.obj_linvel);
    mix(&mut o.obj_angvel, &a.obj_angvel);
    let nlerp = |q: &mut [f32], p: &[f32]| {
        let sign = if q.iter().zip(p).map(|(x, y)| x * y).sum::<f32>() < 0.0 {
            -1.0
        } else {
            1.0
        };
        let mut m = [0f32; 4];
        for c in 0..4 {
            m[c] = p[c] + w * (sign * q[c] - p[c]);
        }
        let n = m.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        for c in 0..4 {
            q[c] = m[c] / n;
        }
    };
    nlerp(&mut o.root_rot, &a.root_rot);
    o.root_rot_expmap = quat::to_expmap(o.root_rot.map(|v| v as f64)).map(|v| v as f32);
    for (q, p) in o.obj_rot.chunks_exact_mut(4).zip(a.obj_rot.chunks_exact(4)) {
        nlerp(q, p);
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(x: f32, yaw: f32, arm: f32) -> State {
        let (s, c) = (yaw / 2.0).sin_cos();
        State {
            root_pos: [x, 0.0, 0.9],
            root_rot: [0.0, 0.0, s, c],
            root_rot_expmap: [0.0, 0.0, yaw],
            joint_rot: vec![arm, 0.0, 0.0],
            joint_vel: vec![0.0; 3],
            // one body 0.5 m ahead of the root along its heading
            body_pos: vec![x + 0.5 * yaw.cos(), 0.5 * yaw.sin(), 1.0],
            body_vel: vec![0.0; 3],
            obj_pos: vec![x, 0.0, 0.12],
            obj_rot: vec![0.0, 0.0, 0.0, 1.0],
            obj_linvel: vec![0.0; 3],
            obj_angvel: vec![0.0; 3],
            ..State::default()
        }
    }

    #[test]
    fn a_blend_moves_from_the_old_frame_aligned_onto_the_new_one() {
        // the old clip ended 3 m away, facing +y, arm at 0.4 rad; the new
        // frame faces +x with the arm at 0
        let from = frame(3.0, std::f32::consts::FRAC_PI_2, 0.4);
        let to = frame(0.0, 0.0, 0.0);
        let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
        let all = blend(&from, &to, 1.0);
        assert_eq!(all.joint_rot, to.joint_rot);
        assert!(all
            .body_pos
            .iter()
            .zip(&to.body_pos)
            .all(|(a, b)| close(*a, *b)));
        // weight 0: the old frame, moved onto the new root and heading, so
        // only the pose differs
        let none = blend(&from, &to, 0.0);
        assert!(close(none.joint_rot[0], 0.4));
        assert!(close(none.root_pos[0], 0.0) && close(none.root_pos[1], 0.0));
        assert!(close(none.body_pos[0], 0.5) && close(none.body_pos[1], 0.0));
        assert!(close(none.root_rot[3].abs(), 1.0));
        // halfway: the joint halfway, the rotation a unit quaternion
        let half = blend(&from, &to, 0.5);
        assert!(close(half.joint_rot[0], 0.2));
        let n: f32 = half.root_rot.iter().map(|v| v * v).sum();
        assert!(close(n, 1.0));
    }
}
