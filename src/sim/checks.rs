//! Accuracy measurements of the simulation, shared by the physics tests and
//! `skillaug bench sim` (so a speed figure is always printed beside what the
//! settings cost in accuracy).
//!
//! - [`pd_tracking`]: with the root held, the PD drives bring the humanoid
//!   from the zero pose to a reference pose; the mean joint angle error after
//!   0.5 s (the physics tests require under 3 degrees).
//! - [`stress`]: worlds under random actions: the largest body speed, the
//!   deepest ground penetration and how far the joint anchors drift apart
//!   (an exactly solved joint keeps them together; the gap measures how well
//!   the solver converges).
//! - [`fk_errors`] (`skillaug check-fk`): every frame of a clip set into
//!   the world and the body positions read back against the clip's.
//! - [`contact_agreement`] and [`ContactAgreement::all`] (`skillaug
//!   check-contact`): simulated contact rules against a clip's contact
//!   flag, frame by frame, and the proximity radius that agrees best.
//! - [`ball_replay`] (`skillaug check-ball`): the humanoid replayed from a
//!   clip frame by frame while its ball is simulated, and how far the ball
//!   follows the clip's; [`ReplayPhysics`] varies the physics it runs
//!   under.

use super::mjcf::Model;
use super::objects::ObjectSpec;
use super::rot;
use super::vec_env::VecEnv;
use super::world::{Part, SimOptions, World};
use crate::augment::ats::start_frames;
use crate::ingest::Ingested;
use crate::motion::clip::AngvelFrame;
use crate::motion::state::State;
use crate::motion::{ClipFrames, MotionLib};
use anyhow::{anyhow, Context, Result};
use rand::{Rng, SeedableRng};
use rapier3d::math::Vector;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Physics that `skillaug check-ball` replays under, to ask whether the
/// simulation set-up is what keeps the clips' own motion from pushing
/// their ball as the clips do (docs/training.md, "The clip's own motion
/// does not keep its ball"). The defaults change nothing: the physics of
/// training and evaluation ([`SimOptions::for_fps`], the MJCF gains, the
/// objects' densities). Set as `check-ball.physics.KEY=VALUE`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReplayPhysics {
    /// Physics steps per policy step, as a multiple of the default's
    /// (the physics rate goes up with them, so the policy step stays
    /// 1/60 s): 4 gives 480 Hz physics and 8 substeps at 60 fps.
    pub rate_factor: usize,
    /// rapier solver iterations per physics step ([`SimOptions`]; default 4).
    pub solver_iterations: usize,
    /// rapier PGS iterations ([`SimOptions`]; default 4).
    pub pgs_iterations: usize,
    /// Factor on every joint's PD stiffness kp.
    pub kp_scale: f64,
    /// Factor on every joint's PD damping kd (kd / kp, the drive's lag
    /// behind a moving target in s, scales by `kd_scale / kp_scale`).
    pub kd_scale: f64,
    /// Density of every object, kg/m^3, in place of its own (the ball's
    /// is 1000: 7.24 kg; a basketball of 0.6 kg and radius 0.12 m has
    /// about 83). Absent: each object's own.
    pub object_density: Option<f32>,
    /// Rotational inertia of the ball: `"solid"` (the default, the
    /// reference's) or `"shell"` (a basketball's, the same mass).
    pub ball_inertia: super::objects::BallInertia,
    /// Angular velocity damping of every object, 1/s, in place of its own
    /// (0.01). Absent: each object's own.
    pub object_angular_damping: Option<f32>,
    /// rapier's contact recycling ([`SimOptions::contact_recycling`];
    /// default on, as in training).
    pub contact_recycling: bool,
}

impl Default for ReplayPhysics {
    fn default() -> Self {
        let d = SimOptions::default();
        ReplayPhysics {
            rate_factor: 1,
            solver_iterations: d.solver_iterations,
            pgs_iterations: d.pgs_iterations,
            kp_scale: 1.0,
            kd_scale: 1.0,
            object_density: None,
            ball_inertia: super::objects::BallInertia::Solid,
            object_angular_damping: None,
            contact_recycling: d.contact_recycling,
        }
    }
}

impl crate::config::Validate for ReplayPhysics {
    /// Counts from 1 to 64, gain factors in (0, 100], a density in
    /// (0, 100000] kg/m^3, an angular damping in [0, 1000] 1/s.
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.count("physics.rate_factor", self.rate_factor as u64, 1, 64)?;
        c.count(
            "physics.solver_iterations",
            self.solver_iterations as u64,
            1,
            1000,
        )?;
        c.count(
            "physics.pgs_iterations",
            self.pgs_iterations as u64,
            1,
            1000,
        )?;
        c.range("physics.kp_scale", self.kp_scale, 1e-6, 100.0)?;
        c.range("physics.kd_scale", self.kd_scale, 1e-6, 100.0)?;
        if let Some(d) = self.object_density {
            c.range("physics.object_density", d as f64, 1e-3, 1e5)?;
        }
        if let Some(d) = self.object_angular_damping {
            c.range("physics.object_angular_damping", d as f64, 0.0, 1000.0)?;
        }
        Ok(())
    }
}

impl ReplayPhysics {
    /// Simulation settings for clips of `fps` frames per second.
    pub fn options(&self, fps: f64) -> SimOptions {
        let d = SimOptions::for_fps(fps);
        SimOptions {
            physics_hz: d.physics_hz * self.rate_factor as f64,
            substeps: d.substeps * self.rate_factor,
            solver_iterations: self.solver_iterations,
            pgs_iterations: self.pgs_iterations,
            contact_recycling: self.contact_recycling,
            ..d
        }
    }

    /// `model` with every joint's kp and kd scaled.
    pub fn model(&self, model: &Model) -> Model {
        let mut m = model.clone();
        for h in m.bodies.iter_mut().flat_map(|b| b.hinges.iter_mut()) {
            h.stiffness *= self.kp_scale;
            h.damping *= self.kd_scale;
        }
        m
    }

    /// `objects` with their density and angular damping replaced, where
    /// set, and the ball's inertia.
    pub fn objects(&self, objects: &mut [ObjectSpec]) {
        super::objects::set_density(objects, self.object_density);
        super::objects::set_ball_inertia(objects, self.ball_inertia);
        super::objects::set_angular_damping(objects, self.object_angular_damping);
    }
}

/// Angle between two exp-map rotations, rad.
pub fn angle_between(a: &[f32], b: &[f32]) -> f32 {
    let v = |x: &[f32]| Vector::new(x[0], x[1], x[2]);
    let qa = rot::from_expmap(v(a));
    let qb = rot::from_expmap(v(b));
    rot::to_expmap(qa.inverse() * qb).length()
}

/// Mean joint error, degrees, after the PD drives pulled the humanoid
/// (root pinned 1 m above `target`'s root, feet clear of the ground, ball
/// parked aside) from the zero pose towards `target` for 0.5 s.
pub fn pd_tracking(model: &Model, opts: &SimOptions, target: &State) -> Result<f32> {
    let mut w = World::new(model, &[ObjectSpec::ball()], opts)?;
    let mut start = target.clone();
    start.root_pos[2] += 1.0;
    start.root_linvel = [0.0; 3];
    start.root_angvel = [0.0; 3];
    start.joint_rot.iter_mut().for_each(|v| *v = 0.0);
    start.joint_vel.iter_mut().for_each(|v| *v = 0.0);
    start.obj_pos = vec![3.0, 3.0, 0.12];
    w.set_state(&start)?;
    w.pin_root(true);
    w.set_joint_targets(&target.joint_rot);
    for _ in 0..(0.5 * opts.physics_hz).round() as usize {
        w.step_physics();
    }
    let g = w.get_state();
    let n = w.n_joints();
    let sum: f32 = (0..n)
        .map(|j| angle_between(&g.joint_rot[3 * j..3 * j + 3], &target.joint_rot[3 * j..]))
        .sum();
    Ok((sum / n as f32).to_degrees())
}

/// `n` start states spread over every clip of `lib`: world `i` starts from
/// clip `i mod clips` at frame `(10 + 7 i) mod frames`.
pub fn spread_starts(lib: &MotionLib, n: usize) -> Result<Vec<State>> {
    (0..n)
        .map(|i| {
            let c = i % lib.clips.len();
            let f = (10 + 7 * i) % lib.frames[c].frames;
            lib.state(c, f)
                .ok_or_else(|| anyhow!("clip {c} has no frame {f}"))
        })
        .collect()
}

/// What [`stress`] saw.
#[derive(Clone, Debug)]
pub struct Stress {
    /// Every body state stayed finite.
    pub finite: bool,
    /// Largest speed of any body or object, m/s.
    pub max_speed: f32,
    /// Lowest point of any collider, m (negative: penetration), and its owner.
    pub lowest: (f32, Part),
    /// Joint anchor gap averaged over joints and policy steps, m.
    pub mean_gap: f32,
    /// Largest joint anchor gap seen, m.
    pub max_gap: f32,
}

/// Step `starts.len()` worlds (one per start state, with the ball) for
/// `seconds` under actions drawn uniformly from [-amplitude, amplitude]
/// around zero (seed `seed`), checking every policy step.
pub fn stress(
    model: &Model,
    opts: &SimOptions,
    starts: &[State],
    seconds: f64,
    amplitude: f32,
    seed: u64,
) -> Result<Stress> {
    let n = starts.len();
    let mut env = VecEnv::new(model, &[ObjectSpec::ball()], opts, n)?;
    for (w, s) in env.worlds.iter_mut().zip(starts) {
        w.set_state(s)?;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let a = env.action_dim();
    let policy_steps = (seconds / opts.policy_dt() as f64).round() as usize;
    let mut out = Stress {
        finite: true,
        max_speed: 0.0,
        lowest: (f32::INFINITY, Part::Ground),
        mean_gap: 0.0,
        max_gap: 0.0,
    };
    let mut gap_sum = 0f64;
    for _ in 0..policy_steps {
        let actions: Vec<f32> = (0..n * a)
            .map(|_| rng.random_range(-amplitude..=amplitude))
            .collect();
        env.step(&actions);
        for w in &env.worlds {
            let (speed, finite) = w.max_speed();
            out.finite &= finite;
            out.max_speed = out.max_speed.max(speed);
            let l = w.lowest_point();
            if l.0 < out.lowest.0 {
                out.lowest = l;
            }
            let (mean, max) = w.joint_gap();
            gap_sum += mean as f64;
            out.max_gap = out.max_gap.max(max);
        }
    }
    out.mean_gap = (gap_sum / (policy_steps * n).max(1) as f64) as f32;
    Ok(out)
}

/// How well a simulated contact rule reproduces a clip's contact flag.
#[derive(Clone, Debug, PartialEq)]
pub struct ContactAgreement {
    /// Valid frames compared.
    pub frames: usize,
    /// Frames whose flag is set.
    pub flagged: usize,
    /// One row per compared frame.
    pub rows: Vec<ContactFrame>,
}

/// One reference frame set into the world: its contact flag beside what
/// the simulated contact rules see.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContactFrame {
    /// The clip's contact flag.
    pub flag: bool,
    /// Smallest hand-to-ball distance of the state set into the world, m.
    pub hand_distance: f32,
    /// A hand touched the ball at some substep of one policy step from the
    /// frame (PD targets = the frame's pose).
    pub touch_any: bool,
    /// A hand touched the ball after the last substep.
    pub touch_last: bool,
}

impl ContactAgreement {
    /// Fraction of frames where `rule(frame)` equals the flag.
    pub fn agreement(&self, rule: impl Fn(&ContactFrame) -> bool) -> f64 {
        let ok = self.rows.iter().filter(|r| rule(r) == r.flag).count();
        ok as f64 / self.rows.len().max(1) as f64
    }

    /// Agreement of the proximity rule at `radius`, m.
    pub fn proximity(&self, radius: f32) -> f64 {
        self.agreement(|r| r.hand_distance < radius)
    }

    /// The frames of every one of `parts` (clips) pooled into one.
    pub fn all<'a>(parts: impl IntoIterator<Item = &'a ContactAgreement>) -> ContactAgreement {
        let (mut rows, mut frames) = (Vec::new(), 0usize);
        for a in parts {
            rows.extend(a.rows.iter().copied());
            frames += a.frames;
        }
        ContactAgreement {
            frames,
            flagged: rows.iter().filter(|r| r.flag).count(),
            rows,
        }
    }

    /// The proximity radius from 0.10 m to 0.40 m (in steps of 0.01 m, the
    /// smallest of equals) whose rule agrees best with the flag, and that
    /// agreement.
    pub fn best_radius(&self) -> (f32, f64) {
        (10..=40)
            .map(|k| {
                let r = k as f32 / 100.0;
                (r, self.proximity(r))
            })
            .fold((0.0, -1.0), |a, b| if b.1 > a.1 { b } else { a })
    }
}

/// Every valid frame of clip `clip` set into a world with `objects`
/// (object 0 is the ball the flag refers to): the rules' verdicts beside
/// the flag (see [`ContactAgreement`]). `None` for a clip without objects.
pub fn contact_agreement(
    lib: &MotionLib,
    clip: usize,
    model: &Model,
    objects: &[ObjectSpec],
    opts: &SimOptions,
) -> Result<Option<ContactAgreement>> {
    let f = &lib.frames[clip];
    if f.n_objects == 0 || objects.is_empty() {
        return Ok(None);
    }
    let mut rows = Vec::new();
    for i in 0..f.frames {
        let Some(s) = f.state(i) else { continue };
        let mut w = World::new(model, objects, opts)?;
        w.set_state(&s)?;
        w.set_joint_targets(&s.joint_rot);
        let near = w.hand_distance(0);
        let c = w.step_with_contacts();
        rows.push(ContactFrame {
            flag: s.contact,
            hand_distance: near,
            touch_any: c.object_hands_any[0],
            touch_last: c.object_hands[0],
        });
    }
    Ok(Some(ContactAgreement {
        frames: rows.len(),
        flagged: rows.iter().filter(|r| r.flag).count(),
        rows,
    }))
}

/// [`contact_agreement`] of every clip of `lib` that has objects, in
/// parallel, each in a world with its objects (read under data root
/// `root`) at its frame rate: `(clip id, agreement)` in clip order.
///
/// # Errors
/// An object that cannot be read, or as [`contact_agreement`].
pub fn contact_agreements(
    lib: &MotionLib,
    model: &Model,
    root: &Path,
) -> Result<Vec<(usize, ContactAgreement)>> {
    per_clip_with_objects(lib, root, &ReplayPhysics::default(), |c, objs, opts| {
        contact_agreement(lib, c, model, objs, opts)
    })
}

/// `check(clip, its objects, its simulation options)` on every clip of
/// `lib` in parallel, each with its objects read under data root `root`
/// and at its frame rate: `(clip id, result)` in clip order for the clips
/// whose check returns `Some`.
///
/// # Errors
/// An object that cannot be read, or the first error of `check`, named by
/// its clip.
pub(crate) fn per_clip_with_objects<T: Send>(
    lib: &MotionLib,
    root: &Path,
    physics: &ReplayPhysics,
    check: impl Fn(usize, &[ObjectSpec], &SimOptions) -> Result<Option<T>> + Sync,
) -> Result<Vec<(usize, T)>> {
    let per_clip = (0..lib.clips.len())
        .into_par_iter()
        .map(|c| {
            let row = &lib.clips[c];
            let mut objs = super::objects::load_all(&row.objects, root)?;
            physics.objects(&mut objs);
            let opts = physics.options(row.fps as f64);
            let found = check(c, &objs, &opts).with_context(|| format!("clip {}", row.name))?;
            Ok(found.map(|t| (c, t)))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(per_clip.into_iter().flatten().collect())
}

/// Forward-kinematics error of one clip, m ([`fk_error`]).
#[derive(Clone, Debug)]
pub struct FkError {
    /// Clip name.
    pub name: String,
    /// Valid frames compared.
    pub frames: usize,
    /// Mean distance over bodies and frames.
    pub mean: f64,
    /// Largest distance.
    pub max: f64,
}

/// Every valid frame of clip `name` set into a world of `model` alone
/// (objects play no part in body positions) with
/// [`World::set_state`], and the body positions read back with
/// [`World::get_state`] compared with those the clip stores.
///
/// # Errors
/// A world that cannot be built or a state it refuses (the message names
/// the clip and frame).
pub fn fk_error(
    name: &str,
    frames: &ClipFrames,
    model: &Model,
    opts: &SimOptions,
) -> Result<FkError> {
    let mut world = World::new(model, &[], opts)?;
    let f = frames;
    let (mut sum, mut max, mut n, mut frames) = (0.0f64, 0.0f64, 0usize, 0usize);
    for i in 0..f.frames {
        let Some(mut s) = f.state(i) else { continue };
        s.obj_pos.clear();
        s.obj_rot.clear();
        s.obj_linvel.clear();
        s.obj_angvel.clear();
        world
            .set_state(&s)
            .with_context(|| format!("{name} frame {i}"))?;
        let p = world.get_state().body_pos;
        for (a, b) in p.chunks_exact(3).zip(s.body_pos.chunks_exact(3)) {
            let d = ((a[0] - b[0]) as f64)
                .hypot((a[1] - b[1]) as f64)
                .hypot((a[2] - b[2]) as f64);
            sum += d;
            max = max.max(d);
            n += 1;
        }
        frames += 1;
    }
    Ok(FkError {
        name: name.to_string(),
        frames,
        mean: sum / n.max(1) as f64,
        max,
    })
}

/// [`fk_error`] of every clip of `clips`, in parallel, each against the
/// MJCF model of its skeleton under data root `root`, at the clip's frame
/// rate with angular velocities in `angvel_frame`.
///
/// # Errors
/// A model that cannot be read, or as [`fk_error`].
pub fn fk_errors(
    clips: &[Ingested],
    root: &Path,
    angvel_frame: AngvelFrame,
) -> Result<Vec<FkError>> {
    let mut models: Vec<(String, Model)> = Vec::new();
    for c in clips {
        let sk = c.layout.skeleton();
        if !models.iter().any(|(n, _)| n == sk.name()) {
            models.push((sk.name().to_string(), Model::for_skeleton(root, sk)?));
        }
    }
    clips
        .par_iter()
        .map(|c| {
            let sk = c.layout.skeleton();
            let m = &models.iter().find(|(n, _)| n == sk.name()).unwrap().1;
            let opts = SimOptions {
                angvel_frame,
                ..SimOptions::for_fps(c.fps)
            };
            fk_error(&c.src.name, &c.frames, m, &opts)
        })
        .collect()
}

/// What the simulation settings cost in accuracy on one model
/// ([`accuracy`]).
#[derive(Clone, Debug)]
pub struct Accuracy {
    /// Mean of the clips' [`pd_tracking`] errors, degrees.
    pub pd_mean_deg: f32,
    /// Largest of them, degrees.
    pub pd_worst_deg: f32,
    /// Clips measured.
    pub clips: usize,
    /// Worlds of the random-action [`stress`] run.
    pub worlds: usize,
    /// What that run saw.
    pub stress: Stress,
}

/// [`pd_tracking`] from the zero pose to every clip's middle frame with the
/// root held, and [`stress`] of 16 worlds ([`spread_starts`]) under
/// full-range random actions for 5 s (seed 7).
///
/// # Errors
/// As [`pd_tracking`], [`spread_starts`] and [`stress`].
pub fn accuracy(lib: &MotionLib, model: &Model, opts: &SimOptions) -> Result<Accuracy> {
    let mut errors = Vec::new();
    for c in 0..lib.clips.len() {
        if let Some(target) = lib.state(c, lib.frames[c].frames / 2) {
            errors.push(pd_tracking(model, opts, &target)?);
        }
    }
    let starts = spread_starts(lib, 16)?;
    Ok(Accuracy {
        pd_mean_deg: errors.iter().sum::<f32>() / errors.len().max(1) as f32,
        pd_worst_deg: errors.iter().copied().fold(0f32, f32::max),
        clips: errors.len(),
        worlds: starts.len(),
        stress: stress(model, opts, &starts, 5.0, 1.0, 7)?,
    })
}

/// What [`ball_replay`] saw on one clip.
#[derive(Clone, Debug)]
pub struct BallReplay {
    /// Policy steps replayed.
    pub steps: usize,
    /// Mean distance of the simulated ball to the clip's, m.
    pub err_mean: f64,
    /// That distance after 0.5 s (or at the last step of a shorter replay), m.
    pub err_half_s: f64,
    /// Downward speed of the clip's ball before its first bounce, m/s.
    pub impact_ref: Option<f64>,
    /// The same of the simulated ball, m/s.
    pub impact_sim: Option<f64>,
    /// Top height of the clip's ball after its first bounce, m.
    pub apex_ref: Option<f64>,
    /// The same of the simulated ball, m.
    pub apex_sim: Option<f64>,
}

/// The ball's first bounce in a series of heights `z` (m) and vertical
/// velocities `vz` (m/s): the first step whose velocity turns from below
/// zero to above it with the ball within 0.3 m of the floor (the ball's
/// radius is 0.12 m). Returns its largest downward speed since the ball
/// last rose, and its top height between the bounce and its next turn
/// downwards; `None` where the series has no bounce (or no turn after it).
pub fn first_bounce(z: &[f64], vz: &[f64]) -> (Option<f64>, Option<f64>) {
    let Some(b) =
        (1..vz.len()).find(|&i| vz[i - 1] < 0.0 && vz[i] > 0.0 && z[i].min(z[i - 1]) < 0.3)
    else {
        return (None, None);
    };
    let fall = (0..b).rev().find(|&i| vz[i] >= 0.0).map_or(0, |i| i + 1);
    let impact = vz[fall..b].iter().map(|v| -v).fold(0.0, f64::max);
    let apex = (b + 1..vz.len())
        .find(|&i| vz[i - 1] > 0.0 && vz[i] <= 0.0)
        .map(|end| z[b..=end].iter().copied().fold(f64::MIN, f64::max));
    (Some(impact), apex)
}

/// Clip `clip` replayed in a world with `objects` (object 0 the ball): the
/// ball starts in the state of the clip's first allowed start frame
/// ([`crate::augment::ats::start_frames`], the RSI rule); before every policy
/// step the humanoid (never the ball) is set to the clip's frame and the PD
/// targets to the next frame's pose, and the simulated ball is compared
/// with the next frame's. `kinematic` makes the humanoid's bodies kinematic
/// ([`World::humanoid_kinematic`]): they move the ball with the clip's
/// velocities and are not pushed back. Ends at the clip's last frame or its
/// first missing one. `None` for a clip without objects or with fewer than
/// two valid frames.
///
/// # Errors
/// A world that cannot be built or a state it refuses (the message names
/// the frame).
pub fn ball_replay(
    lib: &MotionLib,
    clip: usize,
    model: &Model,
    objects: &[ObjectSpec],
    opts: &SimOptions,
    kinematic: bool,
) -> Result<Option<BallReplay>> {
    let f = &lib.frames[clip];
    if f.n_objects == 0 || objects.is_empty() {
        return Ok(None);
    }
    let Some(first) = start_frames(f).iter().position(|&ok| ok) else {
        return Ok(None);
    };
    let mut w = World::new(model, objects, opts)?;
    w.set_state(&f.state(first).expect("valid"))
        .with_context(|| format!("frame {first}"))?;
    w.humanoid_kinematic(kinematic);
    let (mut zs, mut vs, mut zr, mut vr, mut errs) = (vec![], vec![], vec![], vec![], vec![]);
    let half = (0.5 / opts.policy_dt() as f64).round() as usize;
    for i in first..f.frames - 1 {
        let (Some(mut s), Some(next)) = (f.state(i), f.state(i + 1)) else {
            break;
        };
        let g = w.get_state();
        s.obj_pos = g.obj_pos;
        s.obj_rot = g.obj_rot;
        s.obj_linvel = g.obj_linvel;
        s.obj_angvel = g.obj_angvel;
        w.set_state(&s).with_context(|| format!("frame {i}"))?;
        w.set_joint_targets(&next.joint_rot);
        w.step();
        let g = w.get_state();
        let d: f64 = (0..3)
            .map(|k| (g.obj_pos[k] as f64 - next.obj_pos[k] as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        errs.push(d);
        zs.push(g.obj_pos[2] as f64);
        vs.push(g.obj_linvel[2] as f64);
        zr.push(next.obj_pos[2] as f64);
        vr.push(next.obj_linvel[2] as f64);
    }
    if errs.is_empty() {
        return Ok(None);
    }
    let (impact_ref, apex_ref) = first_bounce(&zr, &vr);
    let (impact_sim, apex_sim) = first_bounce(&zs, &vs);
    Ok(Some(BallReplay {
        steps: errs.len(),
        err_mean: errs.iter().sum::<f64>() / errs.len() as f64,
        err_half_s: errs[half.clamp(1, errs.len()) - 1],
        impact_ref,
        impact_sim,
        apex_ref,
        apex_sim,
    }))
}

/// [`ball_replay`] of every clip of `lib` that has objects, with a dynamic
/// and with a kinematic humanoid, in parallel (objects read under data root
/// `root`, each clip at its frame rate, under `physics`): `(clip id,
/// dynamic, kinematic)` in clip order.
///
/// # Errors
/// An object that cannot be read, or as [`ball_replay`] (the message names
/// the clip).
pub fn ball_replays(
    lib: &MotionLib,
    model: &Model,
    root: &Path,
    physics: &ReplayPhysics,
) -> Result<Vec<(usize, BallReplay, BallReplay)>> {
    let model = &physics.model(model);
    let both = per_clip_with_objects(lib, root, physics, |c, objs, opts| {
        let dynamic = ball_replay(lib, c, model, objs, opts, false)?;
        let kinematic = ball_replay(lib, c, model, objs, opts, true)?;
        Ok(dynamic.zip(kinematic))
    })?;
    Ok(both.into_iter().map(|(c, (d, k))| (c, d, k)).collect())
}
