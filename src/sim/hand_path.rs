//! A reference hand that stays on top of its ball while it pushes it
//! (`train.reference_hand = "on-ball"`).
//!
//! docs/training.md ("The clip's own motion does not keep its ball")
//! measured that in the BallPlay captures the ball outruns the hand that
//! pushes it: in the DF clip `run` the wrist moves down at 0.1-3.3 m/s
//! while the ball goes from 0.9 to 4.3 m/s, and the simulated hand that
//! follows the clip, even an infinitely strong (kinematic) one, touches
//! the ball's back and pushes it forward as much as down. This module
//! moves the reference's pushing hand onto the top of its ball instead.
//! In every push window of a ball clip ([`super::push::push_windows`]:
//! the ball descends with a hand body's origin within `hand_radius` of its
//! centre), the hand body nearest the ball at the window's first frame is
//! put directly above the ball's centre, as far from it as it was at that
//! frame, and kept there through the release frame while the ball speeds
//! up; the translation this asks of it,
//! `Delta_i = p_ball,i + (0, 0, d_0) - p_near,i`,
//! is blended in linearly over [`BLEND_S`] before the
//! window's first frame (not before the previous window's release) and
//! out over [`BLEND_S`] after the release (not past the next window's
//! first frame); where one window's blend-out meets the next one's
//! blend-in, the two translations add up. It is reached by inverse
//! kinematics on that side's thorax, shoulder, elbow and wrist joints and
//! the chest joint (15 exp-map components), damped least squares
//! (Levenberg 1944, Marquardt 1963) on that body's position with a small
//! pull towards the clip's own rotations; the rest of the body is the
//! clip's. The captured body
//! positions are moved by the forward kinematics' change, and joint and
//! body velocities are differenced again as ingest derives them
//! ([`crate::motion::clip::backward_diff`]), so the reference stays one
//! consistent motion. The ball, the root and the contact flag stay the
//! clip's. Not in the paper or the reference code; the measurements that
//! chose "on top" over keeping the captured offset are in
//! docs/training.md ("A reference hand on top of its ball").

use super::mjcf::{body_poses, Model};
use super::push::push_windows;
use super::world::hand_bodies;
use crate::motion::clip::{backward_diff, ClipFrames};
use crate::motion::quat::norm;
use crate::motion::MotionLib;
use anyhow::{bail, Result};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// Which hand the training reference follows while it pushes the ball
/// (`train.reference_hand`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ReferenceHand {
    /// The clip's captured hand (the paper's and the reference code's).
    #[default]
    Captured,
    /// The pushing hand put on top of its ball and kept there while the
    /// ball speeds up (module doc).
    OnBall,
}

impl ReferenceHand {
    /// The setting's value as written in a recipe.
    pub fn name(self) -> &'static str {
        match self {
            ReferenceHand::Captured => "captured",
            ReferenceHand::OnBall => "on-ball",
        }
    }
}

/// Seconds over which the hand's translation is blended in before a push
/// window and out after its release (0.1 s: 6 frames of BallPlay's 60 Hz).
pub const BLEND_S: f64 = 0.1;

/// Pull of the solution towards the clip's own rotations, m^2/rad^2
/// (1 rad of change costs as much as 3 cm of the body's error).
const LAMBDA: f64 = 1e-3;

/// The joints solved, by body name (`#` the pushing side: `L` or `R`).
const CHAIN: [&str; 5] = ["#_Thorax", "#_Shoulder", "#_Elbow", "#_Wrist", "Chest"];

/// Gauss-Newton iterations at most per frame.
const ITERATIONS: usize = 40;

/// Step of the forward-difference Jacobian, rad.
const H: f64 = 1e-4;

/// One push window's repaired hand.
#[derive(Clone, Debug, PartialEq)]
pub struct HandRepair {
    /// Clip index in the library.
    pub clip: usize,
    /// The window's first frame.
    pub start: usize,
    /// The release frame (the last frame held on the ball).
    pub release: usize,
    /// `'L'` or `'R'`: the pushing hand.
    pub side: char,
    /// The hand body kept on the ball (model index).
    pub body: usize,
    /// The largest translation asked of the hand, m.
    pub shift: f64,
    /// The largest distance left between that body and its target
    /// after the inverse kinematics, m (where the arm and chest cannot
    /// reach).
    pub residual: f64,
}

/// Put the pushing hand of every push window of `clips` on top of its
/// ball (module doc), in `lib`; the windows are those of
/// [`super::push::push_windows`] with `hand_radius` m and `min_frames`,
/// blended over `blend_s` s. Clips without an object are left as they
/// are. Returns one [`HandRepair`] per window, in clip and frame order.
///
/// # Errors
/// A model without one of the bodies of the solved joints (`L_`/`R_`
/// thorax, shoulder, elbow, wrist; chest), or a clip whose bodies are not
/// the model's, naming the body or the clip.
pub fn repair_hands(
    lib: &mut MotionLib,
    clips: &[usize],
    model: &Model,
    hand_radius: f64,
    min_frames: usize,
    blend_s: f64,
) -> Result<Vec<HandRepair>> {
    let hand = hand_bodies(model);
    let mut out = Vec::new();
    for &clip in clips {
        let fps = lib.clips[clip].fps as f64;
        let f = &mut lib.frames[clip];
        if f.n_objects == 0 {
            continue;
        }
        if f.n_bodies != model.bodies.len() {
            bail!(
                "reference hand on the ball: clip {} has {} bodies, the humanoid model {}",
                lib.clips[clip].name,
                f.n_bodies,
                model.bodies.len()
            );
        }
        let windows = push_windows(f, &hand, hand_radius, min_frames);
        let blend = (blend_s * fps).round() as usize;
        for (k, w) in windows.iter().enumerate() {
            // The blend ends before the next window's first frame.
            let limit = windows.get(k + 1).map_or(f.frames, |n| n.start);
            let lower = if k == 0 {
                0
            } else {
                windows[k - 1].release + 1
            };
            let mut r = repair_window(f, model, &hand, w.start, w.release, blend, lower, limit)?;
            r.clip = clip;
            out.push(r);
        }
        if !windows.is_empty() {
            let (nj, nb) = (f.n_joints, f.n_bodies);
            f.joint_vel = backward_diff(&f.joint_rot, 3 * nj, &f.valid, fps);
            f.body_vel = backward_diff(&f.body_pos, 3 * nb, &f.valid, fps);
        }
    }
    Ok(out)
}

/// Index of the body named `name`.
fn body_named(model: &Model, name: &str) -> Result<usize> {
    match model.bodies.iter().position(|b| b.name == name) {
        Some(i) => Ok(i),
        None => bail!("reference hand on the ball: the humanoid model has no body `{name}`"),
    }
}

fn v3(x: &[f32], b: usize) -> [f64; 3] {
    [x[3 * b] as f64, x[3 * b + 1] as f64, x[3 * b + 2] as f64]
}

/// Forward kinematics of frame `i` of `f` with `joint_rot` in place of
/// its joints: body positions `[B*3]`.
fn fk(model: &Model, f: &ClipFrames, i: usize, joint_rot: &[f32]) -> Vec<f32> {
    let rp = &f.root_pos[3 * i..3 * i + 3];
    let rq = &f.root_rot[4 * i..4 * i + 4];
    body_poses(
        model,
        [rp[0], rp[1], rp[2]],
        [rq[0], rq[1], rq[2], rq[3]],
        joint_rot,
    )
    .0
}

/// Repair one window (module doc) of `f`: frames from `lower` at the
/// earliest to before `limit`.
#[allow(clippy::too_many_arguments)]
fn repair_window(
    f: &mut ClipFrames,
    model: &Model,
    hand: &[bool],
    start: usize,
    release: usize,
    blend: usize,
    lower: usize,
    limit: usize,
) -> Result<HandRepair> {
    let (nj, nb, no) = (f.n_joints, f.n_bodies, f.n_objects);
    let joints_of = |f: &ClipFrames, i: usize| f.joint_rot[i * 3 * nj..(i + 1) * 3 * nj].to_vec();
    let ball = |f: &ClipFrames, i: usize| v3(&f.obj_pos[i * 3 * no..], 0);
    // The hand body nearest the ball at the window's first frame.
    let fk0 = fk(model, f, start, &joints_of(f, start));
    let b0 = ball(f, start);
    let dist = |p: [f64; 3], q: [f64; 3]| norm([p[0] - q[0], p[1] - q[1], p[2] - q[2]]);
    let near = (0..nb)
        .filter(|b| hand[*b])
        .min_by(|a, b| {
            dist(v3(&fk0, *a), b0)
                .partial_cmp(&dist(v3(&fk0, *b), b0))
                .unwrap_or(std::cmp::Ordering::Equal)
        })
        .unwrap_or(0);
    let side = if model.bodies[near].name.starts_with("L_") {
        'L'
    } else {
        'R'
    };
    let mut chain = Vec::new();
    for name in CHAIN {
        chain.push(body_named(model, &name.replace('#', &side.to_string()))? - 1);
    }
    let n = 3 * chain.len();
    let p_near0 = v3(&fk0, near);
    // Directly above the ball's centre, as far from it as at the start.
    let d0 = [0.0, 0.0, dist(p_near0, b0)];
    let delta0: [f64; 3] = std::array::from_fn(|k| b0[k] + d0[k] - p_near0[k]);
    let mut repair = HandRepair {
        clip: 0,
        start,
        release,
        side,
        body: near,
        shift: 0.0,
        residual: 0.0,
    };
    let mut last_delta = [0.0; 3];
    // The offset of the solution from the clip's rotations at the frame
    // before, to start the next frame's solve from.
    let mut carry = vec![0.0f64; n];
    let end = (release + blend).min(limit.saturating_sub(1));
    let first = start.saturating_sub(blend).max(lower);
    for i in first..=end {
        // A missing frame holds no pose to move (the window's own frames
        // are all valid, `push_windows`).
        if !f.valid[i] {
            continue;
        }
        let own = joints_of(f, i);
        let fk_own = fk(model, f, i, &own);
        let delta = if i < start {
            let s = 1.0 - (start - i) as f64 / (blend + 1) as f64;
            delta0.map(|v| v * s)
        } else if i <= release {
            let b = ball(f, i);
            let p = v3(&fk_own, near);
            let d: [f64; 3] = std::array::from_fn(|k| b[k] + d0[k] - p[k]);
            last_delta = d;
            d
        } else {
            let s = 1.0 - (i - release) as f64 / (blend + 1) as f64;
            last_delta.map(|v| v * s)
        };
        repair.shift = repair.shift.max(norm(delta));
        let p_own = v3(&fk_own, near);
        let target: [f64; 3] = std::array::from_fn(|k| p_own[k] + delta[k]);
        let theta_own: Vec<f64> = (0..n)
            .map(|k| own[3 * chain[k / 3] + k % 3] as f64)
            .collect();
        let start_theta: Vec<f64> = (0..n).map(|k| theta_own[k] + carry[k]).collect();
        let theta = solve(
            model,
            Pose { f, i, own: &own },
            &chain,
            near,
            target,
            &theta_own,
            start_theta,
        );
        let mut joints = own.clone();
        for k in 0..n {
            joints[3 * chain[k / 3] + k % 3] = theta[k] as f32;
        }
        carry = (0..n).map(|k| theta[k] - theta_own[k]).collect();
        let fk_new = fk(model, f, i, &joints);
        repair.residual = repair.residual.max(dist(v3(&fk_new, near), target));
        f.joint_rot[i * 3 * nj..(i + 1) * 3 * nj].copy_from_slice(&joints);
        for b in 0..nb {
            for c in 0..3 {
                let k = i * 3 * nb + 3 * b + c;
                f.body_pos[k] += fk_new[3 * b + c] - fk_own[3 * b + c];
            }
        }
    }
    Ok(repair)
}

/// A frame `i` of clip `f` with the joint rotations `own` (`[J*3]`).
struct Pose<'a> {
    f: &'a ClipFrames,
    i: usize,
    own: &'a [f32],
}

/// Damped least squares on the `chain` joints' exp-map components of
/// `pose`: bring body `body` to `target` (m), pulled towards `theta_own`
/// by [`LAMBDA`], from `theta`. Returns the components.
fn solve(
    model: &Model,
    pose: Pose<'_>,
    chain: &[usize],
    body: usize,
    target: [f64; 3],
    theta_own: &[f64],
    mut theta: Vec<f64>,
) -> Vec<f64> {
    let Pose { f, i, own } = pose;
    let n = theta.len();
    let mut joints = own.to_vec();
    let eval = |t: &[f64], joints: &mut Vec<f32>| -> Vec<f64> {
        for k in 0..n {
            joints[3 * chain[k / 3] + k % 3] = t[k] as f32;
        }
        let x = v3(&fk(model, f, i, joints), body);
        (0..3).map(|k| target[k] - x[k]).collect()
    };
    let cost = |r: &[f64], t: &[f64]| -> f64 {
        r.iter().map(|v| v * v).sum::<f64>()
            + LAMBDA * (0..n).map(|k| (t[k] - theta_own[k]).powi(2)).sum::<f64>()
    };
    let mut r = eval(&theta, &mut joints);
    let mut c = cost(&r, &theta);
    let mut mu = 1e-3;
    for _ in 0..ITERATIONS {
        // Forward-difference Jacobian of the positions (= -d r / d theta).
        let m = r.len();
        let mut jac = DMatrix::<f64>::zeros(m, n);
        for k in 0..n {
            let mut t = theta.clone();
            t[k] += H;
            let rk = eval(&t, &mut joints);
            for row in 0..m {
                jac[(row, k)] = (r[row] - rk[row]) / H;
            }
        }
        let mut a = jac.transpose() * &jac;
        let mut g = jac.transpose() * DVector::from_column_slice(&r);
        for p in 0..n {
            g[p] -= LAMBDA * (theta[p] - theta_own[p]);
            a[(p, p)] += LAMBDA;
        }
        let mut improved = false;
        while mu < 1e6 {
            let mut damped = a.clone();
            for p in 0..n {
                damped[(p, p)] += mu;
            }
            let Some(ch) = damped.cholesky() else {
                mu *= 10.0;
                continue;
            };
            let step = ch.solve(&g);
            let t: Vec<f64> = (0..n).map(|k| theta[k] + step[k]).collect();
            let rt = eval(&t, &mut joints);
            let ct = cost(&rt, &t);
            if ct < c {
                theta = t;
                r = rt;
                let gain = c - ct;
                c = ct;
                mu = (mu * 0.3).max(1e-9);
                improved = gain > 1e-12;
                break;
            }
            mu *= 10.0;
        }
        if !improved {
            break;
        }
    }
    theta
}
