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
//!
//! [`reach`] solves the same chain online, for `train.hand_follows_ball`:
//! at every training step inside a push window ([`ball_hands`]) the
//! feed-forward PD targets put the hand above the ball the simulation has,
//! not the clip's ([`crate::rl::humanoid::EnvConfig::ball_hand`]).

use super::mjcf::{body_poses, Model};
use super::push::{hand_near, push_windows};
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

/// Where the online hand of `train.hand_follows_ball` starts following
/// the simulated ball in each push window (`train.hand_follows_ball_from`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FollowFrom {
    /// At the push window's first frame (the ball descending under the
    /// hand).
    #[default]
    Push,
    /// At the first frame of the clip's **ride** before the push: the run
    /// of consecutive frames up to the window's first during which a hand
    /// body of the clip is within the window's hand radius of the ball
    /// (in a dribble, from the catch of the rising ball after its bounce).
    Catch,
}

impl FollowFrom {
    /// The setting's value as written in a recipe.
    pub fn name(self) -> &'static str {
        match self {
            FollowFrom::Push => "push",
            FollowFrom::Catch => "catch",
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
    /// The first frame of full weight: the push window's first frame, or
    /// the first frame of the ride before it ([`FollowFrom::Catch`]).
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
/// As [`ball_hands`], which finds the windows.
pub fn repair_hands(
    lib: &mut MotionLib,
    clips: &[usize],
    model: &Model,
    hand_radius: f64,
    min_frames: usize,
    blend_s: f64,
) -> Result<Vec<HandRepair>> {
    // every window is found on the clip as it comes: a window's repair
    // stops before the next window's first frame, the only frame the next
    // window's hand is chosen at
    let windows = ball_hands(
        lib,
        clips,
        model,
        hand_radius,
        min_frames,
        blend_s,
        FollowFrom::Push,
    )?;
    let mut out = Vec::new();
    for h in &windows {
        let mut r = repair_window(&mut lib.frames[h.clip], model, h);
        r.clip = h.clip;
        out.push(r);
    }
    for &clip in clips {
        if windows.iter().any(|h| h.clip == clip) {
            let fps = lib.clips[clip].fps as f64;
            let f = &mut lib.frames[clip];
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
        None => bail!("pushing hands: the humanoid model has no body `{name}`"),
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

/// The hand a push window pushes with: the hand body nearest the ball at
/// the window's first frame, its side and the joints solved for it.
struct WindowHand {
    /// The hand body (model index).
    body: usize,
    /// `'L'` or `'R'`.
    side: char,
    /// Joint indices of [`CHAIN`] on that side (`[5]`).
    chain: Vec<usize>,
    /// That body's distance from the ball's centre at the first frame, m.
    height: f64,
}

/// The [`WindowHand`] of the window of `f` starting at frame `start`.
fn window_hand(f: &ClipFrames, model: &Model, hand: &[bool], start: usize) -> Result<WindowHand> {
    let (nj, nb, no) = (f.n_joints, f.n_bodies, f.n_objects);
    let fk0 = fk(
        model,
        f,
        start,
        &f.joint_rot[start * 3 * nj..(start + 1) * 3 * nj],
    );
    let b0 = v3(&f.obj_pos[start * 3 * no..], 0);
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
    Ok(WindowHand {
        body: near,
        side,
        chain,
        height: dist(v3(&fk0, near), b0),
    })
}

/// Repair window `h` (module doc) of `f`, over its blends
/// (`h.first..=h.end`).
fn repair_window(f: &mut ClipFrames, model: &Model, h: &BallHand) -> HandRepair {
    let (nj, nb, no) = (f.n_joints, f.n_bodies, f.n_objects);
    let joints_of = |f: &ClipFrames, i: usize| f.joint_rot[i * 3 * nj..(i + 1) * 3 * nj].to_vec();
    let ball = |f: &ClipFrames, i: usize| v3(&f.obj_pos[i * 3 * no..], 0);
    let dist = |p: [f64; 3], q: [f64; 3]| norm([p[0] - q[0], p[1] - q[1], p[2] - q[2]]);
    let (start, release, blend, near, chain) = (h.start, h.release, h.blend, h.body, &h.chain);
    let n = 3 * chain.len();
    let fk0 = fk(model, f, start, &joints_of(f, start));
    let b0 = ball(f, start);
    let p_near0 = v3(&fk0, near);
    // Directly above the ball's centre, as far from it as at the start.
    let d0 = [0.0, 0.0, h.height];
    let delta0: [f64; 3] = std::array::from_fn(|k| b0[k] + d0[k] - p_near0[k]);
    let mut repair = HandRepair {
        clip: h.clip,
        start,
        release,
        side: h.side,
        body: near,
        shift: 0.0,
        residual: 0.0,
    };
    let mut last_delta = [0.0; 3];
    // The offset of the solution from the clip's rotations at the frame
    // before, to start the next frame's solve from.
    let mut carry = vec![0.0f64; n];
    for i in h.first..=h.end {
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
        let mut joints = own.clone();
        let position = |t: &[f64]| {
            for k in 0..n {
                joints[3 * chain[k / 3] + k % 3] = t[k] as f32;
            }
            v3(&fk(model, f, i, &joints), near)
        };
        let theta = solve(position, target, &theta_own, start_theta, ITERATIONS);
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
    repair
}

/// Damped least squares on `n` exp-map components `theta`: bring the
/// body whose position (m) `position` gives for them to `target` (m),
/// pulled towards `theta_own` by [`LAMBDA`], in at most `iterations`
/// Levenberg-Marquardt steps. Returns the components.
fn solve(
    mut position: impl FnMut(&[f64]) -> [f64; 3],
    target: [f64; 3],
    theta_own: &[f64],
    mut theta: Vec<f64>,
    iterations: usize,
) -> Vec<f64> {
    let n = theta.len();
    let mut eval = |t: &[f64]| -> Vec<f64> {
        let x = position(t);
        (0..3).map(|k| target[k] - x[k]).collect()
    };
    let cost = |r: &[f64], t: &[f64]| -> f64 {
        r.iter().map(|v| v * v).sum::<f64>()
            + LAMBDA * (0..n).map(|k| (t[k] - theta_own[k]).powi(2)).sum::<f64>()
    };
    let mut r = eval(&theta);
    let mut c = cost(&r, &theta);
    let mut mu = 1e-3;
    for _ in 0..iterations {
        // Forward-difference Jacobian of the positions (= -d r / d theta).
        let m = r.len();
        let mut jac = DMatrix::<f64>::zeros(m, n);
        for k in 0..n {
            let mut t = theta.clone();
            t[k] += H;
            let rk = eval(&t);
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
            let rt = eval(&t);
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

/// Iterations at most of one online solve ([`reach`]): it starts from the
/// reference's own rotations, a few centimetres from the answer.
const REACH_ITERATIONS: usize = 12;

/// How far [`reach`] moves its hand body from where the reference's pose
/// puts it, m, at most, by default ([`BallHand::reach`]): the largest
/// shift the offline repair asks of DF's and DL's windows is 0.15-0.20 m
/// (docs/training.md, "A reference hand on top of its ball"); a ball
/// farther off is followed only this far, so a stray ball does not twist
/// the chest. `train.hand_follows_ball_reach` is left out of a policy's
/// `policy.meta.json` when it equals this value, so changing it changes
/// how older policies are evaluated.
pub const REACH_MAX_SHIFT: f64 = 0.3;

/// Lead of the online hand target over the simulated ball, s: the PD
/// drives' time constant kd/kp (0.1 s for every BallPlay joint,
/// docs/training.md, "No nearby targets push as the clip does").
pub const REACH_LEAD_S: f64 = 0.1;

/// One push window of a training clip whose pushing hand follows the
/// simulated ball online (`train.hand_follows_ball`, [`reach`]).
#[derive(Clone, Debug, PartialEq)]
pub struct BallHand {
    /// Clip index in the library.
    pub clip: usize,
    /// The window's first frame.
    pub start: usize,
    /// The release frame (the last frame held on the ball).
    pub release: usize,
    /// First frame of the blend before `start` (inclusive).
    pub first: usize,
    /// Last frame of the blend after `release` (inclusive).
    pub end: usize,
    /// Frames of each blend ([`BLEND_S`] at the clip's rate).
    pub blend: usize,
    /// `'L'` or `'R'`: the pushing hand.
    pub side: char,
    /// The hand body held above the ball (model index).
    pub body: usize,
    /// Joint indices solved (`[5]`: thorax, shoulder, elbow, wrist of the
    /// pushing side, chest).
    pub chain: Vec<usize>,
    /// The body's height above the ball's centre, m: its distance from
    /// the ball at the window's first frame.
    pub height: f64,
    /// How far [`reach`] moves the body from where the reference's pose
    /// puts it, m, at most ([`REACH_MAX_SHIFT`] unless
    /// `train.hand_follows_ball_reach` says otherwise).
    pub reach: f64,
}

impl BallHand {
    /// Weight of the online target at clip frame `frame`, in [0, 1]: 1
    /// from `start` through `release`, falling linearly over `blend`
    /// frames on each side, 0 outside `first..=end`.
    pub fn weight(&self, frame: usize) -> f64 {
        if frame < self.first || frame > self.end {
            0.0
        } else if frame < self.start {
            1.0 - (self.start - frame) as f64 / (self.blend + 1) as f64
        } else if frame <= self.release {
            1.0
        } else {
            1.0 - (frame - self.release) as f64 / (self.blend + 1) as f64
        }
    }
}

/// The push windows of `clips` in `lib`, for the online hand
/// (`train.hand_follows_ball`) and the offline repair ([`repair_hands`]):
/// the windows of
/// [`super::push::push_windows`] with `hand_radius` m and `min_frames`,
/// each with the hand that pushes and its blend of `blend_s` s, bounded
/// so that it never reaches the next window's first frame or the previous
/// window's release. Each window's full weight starts where `from` says:
/// at the push window's first frame ([`FollowFrom::Push`]) or at the
/// first frame of the clip's ride before it ([`FollowFrom::Catch`]:
/// `start` moves back over the consecutive frames, after the previous
/// window's release, with a hand body within `hand_radius` m of the
/// ball; the hand body, its side and its height over the ball stay those
/// of the push's first frame). Every window's [`BallHand::reach`] is
/// [`REACH_MAX_SHIFT`] (training sets `train.hand_follows_ball_reach` on
/// them afterwards). Clips without an object have none. In clip and
/// frame order.
///
/// # Errors
/// A model without one of the bodies of the solved joints (`L_`/`R_`
/// thorax, shoulder, elbow, wrist; chest), or a clip whose bodies are not
/// the model's, naming the body or the clip.
pub fn ball_hands(
    lib: &MotionLib,
    clips: &[usize],
    model: &Model,
    hand_radius: f64,
    min_frames: usize,
    blend_s: f64,
    from: FollowFrom,
) -> Result<Vec<BallHand>> {
    let hand = hand_bodies(model);
    let mut out = Vec::new();
    for &clip in clips {
        let f = &lib.frames[clip];
        if f.n_objects == 0 {
            continue;
        }
        if f.n_bodies != model.bodies.len() {
            bail!(
                "pushing hands: clip {} has {} bodies, the humanoid model {}",
                lib.clips[clip].name,
                f.n_bodies,
                model.bodies.len()
            );
        }
        let blend = (blend_s * lib.clips[clip].fps as f64).round() as usize;
        let windows = push_windows(f, &hand, hand_radius, min_frames);
        for (k, w) in windows.iter().enumerate() {
            let limit = windows.get(k + 1).map_or(f.frames, |n| n.start);
            let lower = if k == 0 {
                0
            } else {
                windows[k - 1].release + 1
            };
            let h = window_hand(f, model, &hand, w.start)?;
            let mut start = w.start;
            if from == FollowFrom::Catch {
                while start > lower
                    && f.state(start - 1)
                        .is_some_and(|s| s.obj_pos.len() >= 3 && hand_near(&s, &hand, hand_radius))
                {
                    start -= 1;
                }
            }
            out.push(BallHand {
                clip,
                start,
                release: w.release,
                first: start.saturating_sub(blend).max(lower),
                end: (w.release + blend).min(limit.saturating_sub(1)),
                blend,
                side: h.side,
                body: h.body,
                chain: h.chain,
                height: h.height,
                reach: REACH_MAX_SHIFT,
            });
        }
    }
    Ok(out)
}

/// Position of `body`, m, in the pose of root `root_pos` (m) and
/// `root_rot` (quaternion x, y, z, w) with joints `joint_rot` (`[J*3]`
/// exp-maps, rad): forward kinematics along the body's path from the root
/// only (as [`body_poses`] computes every body).
pub fn body_position(
    model: &Model,
    root_pos: [f32; 3],
    root_rot: [f32; 4],
    joint_rot: &[f32],
    body: usize,
) -> [f64; 3] {
    use crate::motion::quat;
    let mut path = vec![body];
    while let Some(p) = model.bodies[*path.last().unwrap_or(&0)].parent {
        path.push(p);
    }
    let mut rot = root_rot.map(|v| v as f64);
    let mut pos = root_pos.map(|v| v as f64);
    for &i in path.iter().rev().skip(1) {
        let b = &model.bodies[i];
        let o = quat::rotate(rot, b.pos);
        pos = [pos[0] + o[0], pos[1] + o[1], pos[2] + o[2]];
        let j = &joint_rot[3 * (i - 1)..3 * i];
        rot = quat::mul(
            rot,
            quat::from_expmap([j[0] as f64, j[1] as f64, j[2] as f64]),
        );
    }
    pos
}

/// The joint rotations `joint_rot` (`[J*3]` exp-maps, rad; the
/// reference's next frame) with `hand`'s chain moved so that its body,
/// in a pose rooted at `root_pos` / `root_rot`, reaches `target` (m) by
/// damped least squares as the offline repair ([`repair_hands`]), the
/// target first brought within [`BallHand::reach`] of where `joint_rot`
/// puts the body, and the change scaled by `weight` in [0, 1]
/// ([`BallHand::weight`]). Returns the joint rotations and that capped
/// point, m (world). Not in the paper or the reference code.
pub fn reach(
    model: &Model,
    hand: &BallHand,
    root_pos: [f32; 3],
    root_rot: [f32; 4],
    joint_rot: &[f32],
    target: [f64; 3],
    weight: f64,
) -> (Vec<f32>, [f64; 3]) {
    let mut joints = joint_rot.to_vec();
    let own = body_position(model, root_pos, root_rot, joint_rot, hand.body);
    let shift: [f64; 3] = std::array::from_fn(|k| target[k] - own[k]);
    let len = norm(shift);
    let scale = if len > hand.reach {
        hand.reach / len
    } else {
        1.0
    };
    let target: [f64; 3] = std::array::from_fn(|k| own[k] + shift[k] * scale);
    if weight <= 0.0 {
        return (joints, target);
    }
    let chain = &hand.chain;
    let n = 3 * chain.len();
    let theta_own: Vec<f64> = (0..n)
        .map(|k| joint_rot[3 * chain[k / 3] + k % 3] as f64)
        .collect();
    let mut scratch = joint_rot.to_vec();
    let position = |t: &[f64]| {
        for k in 0..n {
            scratch[3 * chain[k / 3] + k % 3] = t[k] as f32;
        }
        body_position(model, root_pos, root_rot, &scratch, hand.body)
    };
    let theta = solve(
        position,
        target,
        &theta_own,
        theta_own.clone(),
        REACH_ITERATIONS,
    );
    for k in 0..n {
        let v = theta_own[k] + weight * (theta[k] - theta_own[k]);
        joints[3 * chain[k / 3] + k % 3] = v as f32;
    }
    (joints, target)
}
