//! The Stitched Trajectory Graph (paper Section 4.4, Appendix B.4, Eq. 20;
//! reference code: Ingrid789/SkillMimic-V2
//! `skillmimic/env/tasks/offline_state_search.py` and
//! `skillmimic/utils/motion_data_handler.py`).
//!
//! Paper direction (default): for each target skill A and every valid state s
//! of the other skills' clips, align s onto each candidate frame of A (root
//! x, y and, by default, heading), find the most similar frame (argmax of S_k,
//! Eq. 19; a clip's first two and last frames are not candidates), and keep
//! the edge s -> frame if beta > tau, with N = min(-ceil(log10 beta), N_max)
//! masked states (Eq. 20; the reference code's floor rule is an option).
//! `per_target` builds the reference code's direction instead: for each frame
//! of A, the best state of each other skill.
//!
//! Speed: S_k under alignment equals S_k between the two states expressed in
//! their own heading frames (positions relative to the root's x, y, turned by
//! minus the heading), except for the root exp-map, which is not invariant
//! under a turn and is computed per pair. So every frame is canonicalised once
//! and each pair costs one pass over ~400 numbers.

use super::{n_masked, MaskRule};
use crate::motion::{quat, MotionLib, Skeleton, State};
use crate::reward::{self, Align, Weights};
use rayon::prelude::*;

/// Settings of the graph.
#[derive(Clone, Copy, Debug)]
pub struct StgParams {
    /// Similarity threshold tau.
    pub tau: f64,
    /// Maximum masked states N_max.
    pub n_max: u32,
    /// Eq. 20 rule.
    pub mask_rule: MaskRule,
    /// Alignment before comparing.
    pub align: Align,
    /// Reference-code direction.
    pub per_target: bool,
}

/// One kept connection: start at (src_clip, src_frame), aligned, then follow
/// skill A from (dst_clip, dst_frame) after `n_masked` masked steps.
#[derive(Clone, Debug, PartialEq)]
pub struct Edge {
    /// Skill A.
    pub target_skill: String,
    /// Class of A.
    pub target_class: u32,
    /// Skill of the start state.
    pub src_skill: String,
    /// Clip of the start state.
    pub src_clip: u32,
    /// Frame of the start state.
    pub src_frame: u32,
    /// Clip of A.
    pub dst_clip: u32,
    /// Frame of A.
    pub dst_frame: u32,
    /// S_k.
    pub beta: f64,
    /// Masked states.
    pub n_masked: u32,
    /// Turn applied to the start state about its root, rad.
    pub align_yaw: f32,
    /// Then shift x, m.
    pub align_dx: f32,
    /// Then shift y, m.
    pub align_dy: f32,
}

impl Edge {
    /// The start state of this edge, moved onto the target frame.
    pub fn aligned_start(&self, lib: &MotionLib) -> Option<State> {
        let s = lib.state(self.src_clip as usize, self.src_frame as usize)?;
        let p = [s.root_pos[0] as f64, s.root_pos[1] as f64];
        let to = [p[0] + self.align_dx as f64, p[1] + self.align_dy as f64];
        Some(reward::apply_alignment(&s, self.align_yaw as f64, p, to))
    }
}

/// Per-skill counts.
#[derive(Clone, Debug, PartialEq)]
pub struct SkillSummary {
    /// Skill A.
    pub target_skill: String,
    /// States considered.
    pub states: u32,
    /// Edges kept.
    pub kept: u32,
    /// States dropped.
    pub dropped: u32,
    /// Kept edges per N.
    pub n_hist: Vec<u32>,
    /// Median beta of kept edges.
    pub beta_median: Option<f64>,
}

/// A frame in its own heading frame, flattened per reward term.
struct Canon {
    yaw: f64,
    root_xy: [f64; 2],
    root_q: [f64; 4],
    joints: Vec<f64>,
    kp: Vec<f64>,
    kv: Vec<f64>,
    jv: Vec<f64>,
    op: Vec<f64>,
    oq: Vec<f64>,
    ov: Vec<f64>,
    ow: Vec<f64>,
    rel: Vec<f64>,
}

fn canon(s: &State, sk: Skeleton, align: Align) -> Canon {
    let yaw = if align.yaw {
        quat::heading(s.root_rot)
    } else {
        0.0
    };
    let root_xy = [s.root_pos[0] as f64, s.root_pos[1] as f64];
    let pivot = if align.xy { root_xy } else { [0.0, 0.0] };
    // Express s in its heading frame: turn by -yaw about its root, root at the origin.
    let c = reward::apply_alignment(s, -yaw, pivot, [0.0, 0.0]);
    let f = |v: &[f32]| v.iter().map(|x| *x as f64).collect::<Vec<f64>>();
    let kp = reward::key_points(&c, sk);
    let mut kv: Vec<f64> = f(&c.root_linvel);
    for b in sk.key_bodies() {
        kv.extend(f(&c.body_vel[3 * b..3 * b + 3]));
    }
    let mut rel = Vec::new();
    for o in c.obj_pos.chunks_exact(3) {
        for k in kp.chunks_exact(3) {
            rel.extend((0..3).map(|i| k[i] - o[i] as f64));
        }
    }
    Canon {
        yaw,
        root_xy,
        root_q: s.root_rot.map(|v| v as f64),
        joints: f(&s.joint_rot),
        kp,
        kv,
        jv: f(&s.joint_vel),
        op: f(&c.obj_pos),
        oq: f(&c.obj_rot),
        ov: f(&c.obj_linvel),
        ow: f(&s.obj_angvel),
        rel,
    }
}

fn mse(a: &[f64], b: &[f64]) -> f64 {
    if a.is_empty() {
        return 0.0;
    }
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>() / a.len() as f64
}

/// S_k of `s` aligned onto target frame `t` (equal to
/// [`reward::similarity`]`(t_state, s_state)`).
fn sim(t: &Canon, s: &Canon, w: &Weights) -> f64 {
    // Root rotation: exp-map of the turned start vs. the target's, per component.
    let turn = quat::from_expmap([0.0, 0.0, t.yaw - s.yaw]);
    let e_s = quat::to_expmap(quat::mul(turn, s.root_q));
    let e_t = quat::to_expmap(t.root_q);
    let n_rot = 3 + t.joints.len();
    let root_sq: f64 = (0..3).map(|i| (e_s[i] - e_t[i]).powi(2)).sum();
    let joint_sq: f64 = t
        .joints
        .iter()
        .zip(&s.joints)
        .map(|(a, b)| (a - b) * (a - b))
        .sum();
    let r = (root_sq + joint_sq) / n_rot as f64;
    // object quaternions: sign-agnostic
    let mut oq = 0.0;
    for (a, b) in t.oq.chunks_exact(4).zip(s.oq.chunks_exact(4)) {
        let d: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
        let sg = if d < 0.0 { -1.0 } else { 1.0 };
        oq += a
            .iter()
            .zip(b)
            .map(|(x, y)| (x - sg * y).powi(2))
            .sum::<f64>();
    }
    let oq = if t.oq.is_empty() {
        0.0
    } else {
        oq / t.oq.len() as f64
    };
    let exponent = w.p * mse(&t.kp, &s.kp)
        + w.r * r
        + w.pv * mse(&t.kv, &s.kv)
        + w.rv * mse(&t.jv, &s.jv)
        + w.op * mse(&t.op, &s.op)
        + w.or * oq
        + w.opv * mse(&t.ov, &s.ov)
        + w.orv * mse(&t.ow, &s.ow)
        + w.rel * mse(&t.rel, &s.rel);
    (-exponent).exp()
}

/// Candidate target frames of a clip: valid frames, without the first two and
/// the last (all valid frames if that leaves none), as the reference code's
/// search skips them (Ingrid789/SkillMimic-V2
/// `skillmimic/utils/motion_data_handler.py`,
/// `_randskill_find_class_most_similarity_state`).
fn candidates(lib: &MotionLib, clip: usize) -> Vec<usize> {
    let c = &lib.frames[clip];
    let inner: Vec<usize> = (2..c.frames.saturating_sub(1))
        .filter(|i| c.valid[*i])
        .collect();
    if inner.is_empty() {
        (0..c.frames).filter(|i| c.valid[*i]).collect()
    } else {
        inner
    }
}

/// Build the graph for every skill of `lib`.
pub fn build(lib: &MotionLib, w: &Weights, p: &StgParams) -> (Vec<Edge>, Vec<SkillSummary>) {
    let sk = lib.skeleton;
    let owned: Vec<Vec<Option<Canon>>> = lib
        .frames
        .par_iter()
        .map(|c| {
            (0..c.frames)
                .map(|i| c.state(i).map(|s| canon(&s, sk, p.align)))
                .collect()
        })
        .collect();
    let canons = &owned;
    let skills = lib.skills();
    let mut edges = Vec::new();
    let mut summary = Vec::new();
    for a in &skills {
        let a_clips = lib.clips_of(a);
        let a_class = lib.clips[a_clips[0]].class as u32;
        // (clip, frame) pairs
        let a_cands: Vec<(usize, usize)> = a_clips
            .iter()
            .flat_map(|&c| candidates(lib, c).into_iter().map(move |f| (c, f)))
            .collect();
        let mut kept: Vec<Edge> = Vec::new();
        let mut states = 0u32;
        let best_of =
            |s: &Canon, cands: &[(usize, usize)], s_is_target: bool| -> (f64, (usize, usize)) {
                let mut best = (-1.0, cands[0]);
                for &(c, f) in cands {
                    let other = canons[c][f].as_ref().expect("candidates are valid");
                    let b = if s_is_target {
                        sim(s, other, w)
                    } else {
                        sim(other, s, w)
                    };
                    if b > best.0 {
                        best = (b, (c, f));
                    }
                }
                best
            };
        let make = |src: (usize, usize), dst: (usize, usize), beta: f64| -> Option<Edge> {
            let n = n_masked(beta, p.tau, p.n_max, p.mask_rule)?;
            let (s, t) = (
                canons[src.0][src.1].as_ref()?,
                canons[dst.0][dst.1].as_ref()?,
            );
            let yaw = if p.align.yaw {
                quat::wrap_angle(t.yaw - s.yaw)
            } else {
                0.0
            };
            let (dx, dy) = if p.align.xy {
                (t.root_xy[0] - s.root_xy[0], t.root_xy[1] - s.root_xy[1])
            } else {
                (0.0, 0.0)
            };
            Some(Edge {
                target_skill: a.clone(),
                target_class: a_class,
                src_skill: lib.clips[src.0].skill.clone(),
                src_clip: src.0 as u32,
                src_frame: src.1 as u32,
                dst_clip: dst.0 as u32,
                dst_frame: dst.1 as u32,
                beta,
                n_masked: n,
                align_yaw: yaw as f32,
                align_dx: dx as f32,
                align_dy: dy as f32,
            })
        };
        // every valid frame of clip c
        let frames_of = |c: usize| {
            (0..lib.frames[c].frames)
                .filter(move |f| canons[c][*f].is_some())
                .map(move |f| (c, f))
        };
        if !p.per_target {
            let sources: Vec<(usize, usize)> = (0..lib.clips.len())
                .filter(|c| lib.clips[*c].skill != *a)
                .flat_map(frames_of)
                .collect();
            states = sources.len() as u32;
            let found: Vec<Option<Edge>> = sources
                .par_iter()
                .map(|&src| {
                    let s = canons[src.0][src.1].as_ref().unwrap();
                    let (beta, dst) = best_of(s, &a_cands, false);
                    make(src, dst, beta)
                })
                .collect();
            kept.extend(found.into_iter().flatten());
        } else {
            let targets: Vec<(usize, usize)> = a_clips.iter().flat_map(|&c| frames_of(c)).collect();
            for b in skills.iter().filter(|b| *b != a) {
                let b_cands: Vec<(usize, usize)> = lib
                    .clips_of(b)
                    .into_iter()
                    .flat_map(|c| candidates(lib, c).into_iter().map(move |f| (c, f)))
                    .collect();
                states += targets.len() as u32;
                let found: Vec<Option<Edge>> = targets
                    .par_iter()
                    .map(|&dst| {
                        let t = canons[dst.0][dst.1].as_ref().unwrap();
                        let (beta, src) = best_of(t, &b_cands, true);
                        make(src, dst, beta)
                    })
                    .collect();
                kept.extend(found.into_iter().flatten());
            }
        }
        let mut hist = vec![0u32; p.n_max as usize + 1];
        for e in &kept {
            hist[e.n_masked as usize] += 1;
        }
        let mut betas: Vec<f64> = kept.iter().map(|e| e.beta).collect();
        betas.sort_by(|x, y| x.total_cmp(y));
        summary.push(SkillSummary {
            target_skill: a.clone(),
            states,
            kept: kept.len() as u32,
            dropped: states - kept.len() as u32,
            n_hist: hist,
            beta_median: betas.get(betas.len() / 2).copied(),
        });
        edges.extend(kept);
    }
    (edges, summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reward::tests::state;
    use crate::reward::{similarity, DatasetKind};

    const SK: Skeleton = Skeleton::MocapHumanoid;

    fn canonical_similarity(t: &State, s: &State, sk: Skeleton, w: &Weights, align: Align) -> f64 {
        sim(&canon(t, sk, align), &canon(s, sk, align), w)
    }

    #[test]
    fn the_stg_canonical_similarity_equals_the_aligned_one() {
        let w = Weights::sm(DatasetKind::BallPlay);
        for (i, j) in [(1u64, 2u64), (3, 9), (10, 11)] {
            let (a, mut b) = (state(i), state(j));
            b.root_rot = quat::from_expmap([0.1, 0.2, -2.5]).map(|v| v as f32);
            b.root_rot_expmap = [0.1, 0.2, -2.5];
            b.root_pos = [-3.0, 4.0, 0.8];
            for align in [
                Align::default(),
                Align {
                    xy: true,
                    yaw: false,
                },
            ] {
                let want = similarity(&a, &b, SK, &w, align);
                let got = canonical_similarity(&a, &b, SK, &w, align);
                assert!(
                    (want - got).abs() <= 1e-6 * want.max(1e-12),
                    "{want} vs {got}"
                );
            }
        }
    }
}
