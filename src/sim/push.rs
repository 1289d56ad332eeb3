//! Push search: are there PD targets near a clip's own that make the
//! simulated ball leave the hand as the clip's ball does?
//!
//! [`crate::sim::checks::ball_replay`] showed that the clips' own motion,
//! set into the simulator frame by frame, does not keep their ball up. This
//! module asks the next question of issue 16's item 5 ("better targets you
//! find and measure by open-loop replay"): over each *push window* of a
//! ball clip (consecutive frames where the clip's ball descends with a hand
//! body's origin within `hand_radius` of its centre, [`push_windows`]), the
//! humanoid and the ball start from the clip's state at the window's first
//! frame and the humanoid is driven by PD alone (no frame is set again, as
//! in training) towards the next frame's joint rotations plus an offset
//! held over the window on a group of joints: the arms (shoulders, elbows,
//! wrists) or the whole upper body (the arms plus the torso, spine, chest,
//! thorax and neck joints). The offset is searched by the cross-entropy
//! method (a Gaussian over offsets, refitted to its best `elites` of
//! `population` draws for `iterations` rounds; Rubinstein and Kroese, *The
//! Cross-Entropy Method*, 2004) to bring the ball's velocity and position
//! one frame after the window (the release) to the clip's; the cost is
//! `|v - v_ref|^2 + 25 |p - p_ref|^2` (m^2/s^2; 25 s^-2 weighs 0.2 m of
//! position like 1 m/s of velocity). The zero offset is the clip's own
//! targets; the best offset ever drawn (zero included) is reported, so a
//! search never reports worse than the replay.
//!
//! With `objective = "catch"` the cost is measured later, at the window's
//! *catch frame* ([`catch_frame`]: the first frame after the ball's next
//! bounce where a hand body is again within `hand_radius` of the clip's
//! ball), the humanoid tracking the clip's own next frames after the
//! release: `|v - v_ref|^2 + 25 |(p - r) - (p_ref - r_ref)|^2` with `r`
//! the root's position, so the cost asks where the ball comes back to the
//! hand after the simulated floor has taken its share of the ball's
//! horizontal speed, not how it leaves the hand.
//!
//! With `objective = "sm"` the search instead maximises the SM reward
//! (paper Eqs. 12-17, training's weights and reward options) summed over
//! the window and the `sm_frames` frames after it, the humanoid tracking
//! the clip's own next frames after the release: is a harder push what the
//! reward the policy learns from asks for? Whatever the objective, the
//! offsets `skillaug check-ball` reports carry their SM sum ([`SmScore`])
//! and their cost at the catch frame.
//!
//! Measured figures are in docs/training.md ("No nearby targets push as the
//! clip does").

use super::checks::ReplayPhysics;
use super::mjcf::Model;
use super::world::{hand_bodies, joint_rates, SimOptions, World};
use super::ObjectSpec;
use crate::motion::clip::ClipFrames;
use crate::motion::{MotionLib, Skeleton, State};
use crate::reward::{self, DatasetKind, RewardOptions, WeightOverrides, Weights};
use anyhow::{Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Settings of the push search (`[check-ball]` table of `skillaug
/// check-ball`; off unless `push_search`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PushConfig {
    /// Run the push search after the replay table.
    pub push_search: bool,
    /// A frame belongs to a push window when a hand body's origin (wrist or
    /// finger joint) is within this distance of the ball's centre, m (the
    /// clips hold it at 0.09-0.11 m while they push, inside the ball's
    /// 0.12 m radius).
    pub hand_radius: f64,
    /// Shortest push window, frames.
    pub min_frames: usize,
    /// Offsets drawn per round.
    pub population: usize,
    /// Best draws the Gaussian is refitted to.
    pub elites: usize,
    /// Rounds.
    pub iterations: usize,
    /// Standard deviation of the first round's Gaussian, rad per axis.
    pub init_sd: f64,
    /// Physics of the replays and the search (`check-ball.physics.KEY`;
    /// the defaults are training's).
    pub physics: ReplayPhysics,
    /// What the search optimises: the ball at the release (`"ball"`, the
    /// module doc's cost), the ball at the catch frame relative to the root
    /// (`"catch"`, module doc) or the SM reward (`"sm"`: its sum over the
    /// window and the `sm_frames` frames after it, [`SmScore`]).
    pub objective: PushObjective,
    /// Frames after the release over which the SM reward is also summed
    /// (the humanoid then tracks the clip's own next frames), so that the
    /// ball's bounce after the push counts.
    pub sm_frames: usize,
    /// Replacements of the SM weights the replays are scored with
    /// (`check-ball.reward_weights = { opv = 0.5 }`, as
    /// `train.reward_weights`); none by default: the paper's Table 8.
    pub reward_weights: WeightOverrides,
    /// The hand the replays and the search start from and track:
    /// `"captured"` (the clip's) or `"on-ball"`, the pushing hand put on
    /// top of its ball ([`super::hand_path`], as `train.reference_hand`).
    pub reference_hand: super::hand_path::ReferenceHand,
}

/// What a push search optimises ([`PushConfig::objective`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PushObjective {
    /// The ball's velocity and position at the release against the clip's.
    #[default]
    Ball,
    /// The SM reward (paper Eqs. 12-17, training's weights and options)
    /// summed over the window and [`PushConfig::sm_frames`] frames after.
    Sm,
    /// The ball's velocity and its position relative to the root at the
    /// window's [`catch_frame`] against the clip's.
    Catch,
}

impl PushObjective {
    /// The recipe's name of the objective.
    pub fn name(self) -> &'static str {
        match self {
            PushObjective::Ball => "ball",
            PushObjective::Sm => "sm",
            PushObjective::Catch => "catch",
        }
    }
}

impl Default for PushConfig {
    fn default() -> Self {
        PushConfig {
            push_search: false,
            hand_radius: 0.15,
            min_frames: 3,
            population: 48,
            elites: 8,
            iterations: 12,
            init_sd: 0.3,
            physics: ReplayPhysics::default(),
            objective: PushObjective::Ball,
            sm_frames: 40,
            reward_weights: WeightOverrides::default(),
            reference_hand: super::hand_path::ReferenceHand::Captured,
        }
    }
}

impl crate::config::Validate for PushConfig {
    /// Counts at least 1, elites at most the population, radius and
    /// standard deviation positive and finite.
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.range("hand_radius", self.hand_radius, 1e-3, 10.0)?;
        c.count("min_frames", self.min_frames as u64, 1, 10_000)?;
        c.count("population", self.population as u64, 1, 100_000)?;
        c.count("elites", self.elites as u64, 1, self.population as u64)?;
        c.count("iterations", self.iterations as u64, 0, 10_000)?;
        c.range("init_sd", self.init_sd, 1e-6, 10.0)?;
        c.count("sm_frames", self.sm_frames as u64, 0, 10_000)?;
        self.reward_weights.check(stage)?;
        crate::config::Validate::validate(&self.physics, stage)
    }
}

/// A push window of one clip: the ball descends with a hand on it over
/// frames `start..release` and is measured at frame `release`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PushWindow {
    /// First frame (a frame an episode may start from,
    /// [`crate::augment::ats::start_frames`]).
    pub start: usize,
    /// The frame after the window's last, where the ball is compared.
    pub release: usize,
    /// Where the clip's hand meets the ball again after its bounce
    /// ([`catch_frame`]; `None` when the clip has no such frame).
    pub catch: Option<usize>,
}

/// The push windows of a clip: maximal runs of at least `min_frames` valid
/// frames where object 0 descends (`v_z < 0`) and the nearest hand body
/// origin (`hand` marks the hand bodies) is within `hand_radius` m of its
/// centre, starting at an allowed start frame, with a valid frame after.
pub fn push_windows(
    f: &ClipFrames,
    hand: &[bool],
    hand_radius: f64,
    min_frames: usize,
) -> Vec<PushWindow> {
    let allowed = crate::augment::ats::start_frames(f);
    let pushing = |i: usize| -> bool {
        let Some(s) = f.state(i) else { return false };
        s.obj_pos.len() >= 3 && s.obj_linvel[2] < 0.0 && hand_near(&s, hand, hand_radius)
    };
    let mut out = Vec::new();
    let mut i = 0;
    while i < f.frames {
        if !(allowed[i] && pushing(i)) {
            i += 1;
            continue;
        }
        let mut end = i + 1;
        while end < f.frames && pushing(end) {
            end += 1;
        }
        if end - i >= min_frames && end < f.frames && f.valid[end] {
            let mut w = PushWindow {
                start: i,
                release: end,
                catch: None,
            };
            w.catch = catch_frame(f, hand, hand_radius, w);
            out.push(w);
        }
        i = end;
    }
    out
}

/// Whether a hand body origin of `s` (`hand` marks the hand bodies) is
/// within `hand_radius` m of object 0's centre (`s` has an object).
pub(crate) fn hand_near(s: &State, hand: &[bool], hand_radius: f64) -> bool {
    hand.iter().enumerate().filter(|(_, h)| **h).any(|(b, _)| {
        let d2: f64 = (0..3)
            .map(|k| (s.body_pos[b * 3 + k] as f64 - s.obj_pos[k] as f64).powi(2))
            .sum();
        d2.sqrt() < hand_radius
    })
}

/// The catch frame of window `w` of clip `f`: after the release, the
/// first frame whose object 0 rises (`v_z > 0`, the bounce), then the
/// first frame after that with a hand body origin (`hand` marks the hand
/// bodies) within `hand_radius` m of the ball's centre. `None` when a
/// frame is missing or the clip ends before (the search then has no catch
/// to score: [`PushObjective::Catch`] falls back to the release's cost).
pub fn catch_frame(
    f: &ClipFrames,
    hand: &[bool],
    hand_radius: f64,
    w: PushWindow,
) -> Option<usize> {
    let mut bounced = false;
    for i in w.release + 1..f.frames {
        let s = f.state(i)?;
        if s.obj_pos.len() < 3 {
            return None;
        }
        if !bounced {
            bounced = s.obj_linvel[2] > 0.0;
        } else if hand_near(&s, hand, hand_radius) {
            return Some(i);
        }
    }
    None
}

/// Joints (index j drives body j + 1) of the arms (`upper = false`:
/// shoulders, elbows, wrists) or of the upper body (`upper = true`: also
/// the torso, spine, chest, thorax and neck), by body name.
pub fn push_joints(model: &Model, upper: bool) -> Vec<usize> {
    let arm = ["Shoulder", "Elbow", "Wrist"];
    let trunk = ["Torso", "Spine", "Chest", "Thorax", "Neck"];
    model
        .bodies
        .iter()
        .enumerate()
        .skip(1)
        .filter(|(_, b)| {
            arm.iter().any(|k| b.name.contains(k))
                || (upper && trunk.iter().any(|k| b.name.contains(k)))
        })
        .map(|(i, _)| i - 1)
        .collect()
}

/// The SM reward of an open-loop replay against the clip's frames: summed
/// over its steps, and each factor's mean per step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SmScore {
    /// Steps scored: the window's and up to [`PushConfig::sm_frames`] after
    /// it (fewer where the clip ends or a frame is missing).
    pub steps: usize,
    /// Sum of the SM reward over those steps.
    pub sum: f64,
    /// Mean body factor r_b.
    pub body: f64,
    /// Mean object factor r_o.
    pub object: f64,
    /// Mean relative factor r_rel.
    pub rel: f64,
    /// Mean contact factor r_cg.
    pub cg: f64,
}

/// How a replay scores the SM reward ([`PushObjective::Sm`] and the
/// table's SM columns): the skeleton, training's SM weights (with
/// [`PushConfig::reward_weights`]) and reward options, and the frames
/// after the release.
#[derive(Clone, Copy)]
struct Scorer {
    sk: Skeleton,
    weights: Weights,
    opts: RewardOptions,
    frames: usize,
}

impl Scorer {
    fn of(lib: &MotionLib, cfg: &PushConfig) -> Scorer {
        Scorer {
            sk: lib.skeleton,
            weights: cfg
                .reward_weights
                .apply(Weights::sm(DatasetKind::of_library(lib))),
            opts: RewardOptions::default(),
            frames: cfg.sm_frames,
        }
    }
}

/// The ball one frame after a window, replayed under PD from the clip's
/// state at `w.start` with targets = next frame + `offset` on `joints`;
/// with a scorer, the replay goes on with the clip's own targets for its
/// frames after the release and the SM reward of every step is summed;
/// with `catch`, it goes on to the window's catch frame (the clip's own
/// targets after the release) and the ball is also measured there.
#[derive(Clone)]
struct Outcome {
    /// The ball's cost at the release (module doc).
    cost: f64,
    vel: [f64; 3],
    /// The ball's cost at the catch frame (module doc), when replayed to it.
    catch_cost: Option<f64>,
    /// How far the ball is at the catch frame from where the clip's is,
    /// both relative to the root, m.
    catch_err: Option<f64>,
    sm: Option<SmScore>,
}

#[allow(clippy::too_many_arguments)]
fn replay(
    world: &mut World,
    f: &ClipFrames,
    w: PushWindow,
    joints: &[usize],
    offset: &[f32],
    rates: bool,
    scorer: Option<&Scorer>,
    catch: bool,
) -> Result<Outcome> {
    let start = f.state(w.start).context("start frame not valid")?;
    world.set_state(&start)?;
    let mut score = SmScore::default();
    let (mut at_release, mut at_catch) = (None, None);
    let scored_until = scorer.map_or(w.release, |sc| w.release + sc.frames);
    let catch = w.catch.filter(|_| catch);
    // the world stands at clip frame i at the top of each pass; the last
    // pass only takes the states measured there
    let end = scored_until.max(catch.unwrap_or(0)).min(f.frames - 1);
    for i in w.start..=end {
        if i == w.release {
            at_release = Some(world.get_state());
        }
        if Some(i) == catch {
            at_catch = Some(world.get_state());
        }
        if i == end {
            break;
        }
        let Some(next) = f.state(i + 1) else {
            // a missing frame ends the scored part; the window's frames
            // are all valid (push_windows)
            anyhow::ensure!(i >= w.release, "window frame {} not valid", i + 1);
            break;
        };
        let rates = rates.then(|| joint_rates(&next.joint_rot, &next.joint_vel));
        let mut t = next.joint_rot.clone();
        if i < w.release {
            for (k, &j) in joints.iter().enumerate() {
                for a in 0..3 {
                    t[j * 3 + a] += offset[k * 3 + a];
                }
            }
        }
        match rates {
            // the training's own path: residual action 0 about the frame
            Some(r) => world.apply_action_with_rates(&crate::rl::humanoid::feed_forward(&t), &r),
            None => world.set_joint_targets(&t),
        }
        match scorer.filter(|_| i < scored_until) {
            Some(sc) => {
                let c = world.step_with_contacts().reward_contacts(
                    sc.sk.contact_penalty_bodies(),
                    sc.opts.contact_detect,
                    sc.opts.contact_radius,
                );
                let g = world.get_state();
                let r = reward::sm_reward(&g, &next, &c, sc.sk, &sc.weights, &sc.opts, None);
                score.steps += 1;
                score.sum += r.total;
                score.body += r.body;
                score.object += r.object;
                score.rel += r.rel;
                score.cg += r.cg;
            }
            None => world.step(),
        }
    }
    // the release is at or before `end`, and the loop errs before it
    let g = at_release.context("the replay stopped before the release frame")?;
    let (cost, _) = ball_cost(
        &g,
        &f.state(w.release).context("release frame not valid")?,
        false,
    );
    let (catch_cost, catch_err) = match catch {
        Some(c) => {
            // catch_frame only returns frames with every frame up to them
            // valid, so a replay cannot stop short of one; if it did, err
            let at = at_catch.with_context(|| {
                format!("the replay stopped at a missing frame before the catch frame {c}")
            })?;
            let r = f.state(c).context("catch frame not valid")?;
            let (cost, err) = ball_cost(&at, &r, true);
            (Some(cost), Some(err))
        }
        None => (None, None),
    };
    let sm = scorer.map(|_| {
        let n = score.steps.max(1) as f64;
        SmScore {
            body: score.body / n,
            object: score.object / n,
            rel: score.rel / n,
            cg: score.cg / n,
            ..score
        }
    });
    Ok(Outcome {
        cost,
        vel: std::array::from_fn(|k| g.obj_linvel[k] as f64),
        catch_cost,
        catch_err,
        sm,
    })
}

/// The module doc's cost of the simulated state `g` against the clip's
/// `r`, `|v - v_ref|^2 + 25 |p - p_ref|^2` (m^2/s^2), and the distance
/// `|p - p_ref|` (m), with p the ball's position, relative to the root's
/// when `from_root` (the catch) and in the world otherwise (the release).
fn ball_cost(g: &State, r: &State, from_root: bool) -> (f64, f64) {
    let p = |s: &State, k: usize| {
        s.obj_pos[k] as f64 - if from_root { s.root_pos[k] as f64 } else { 0.0 }
    };
    let dv: f64 = (0..3)
        .map(|k| (g.obj_linvel[k] as f64 - r.obj_linvel[k] as f64).powi(2))
        .sum();
    let dp: f64 = (0..3).map(|k| (p(g, k) - p(r, k)).powi(2)).sum();
    (dv + 25.0 * dp, dp.sqrt())
}

impl Outcome {
    /// What a search minimises: the ball's cost at the release or at the
    /// catch (the release's where the window has no catch frame), or the
    /// negated SM sum.
    fn key(&self, objective: PushObjective) -> f64 {
        match (objective, self.sm) {
            (PushObjective::Sm, Some(s)) => -s.sum,
            (PushObjective::Catch, _) => self.catch_cost.unwrap_or(self.cost),
            _ => self.cost,
        }
    }
}

/// The best offset found for one window and joint group.
#[derive(Clone, Debug)]
pub struct PushSearch {
    /// Ball velocity at the release, m/s.
    pub vel: [f64; 3],
    /// Cost at the release (module doc), m^2/s^2.
    pub cost: f64,
    /// Cost at the catch frame (module doc), m^2/s^2: every search's best
    /// offset and the clip's own targets are replayed to it; `None` where
    /// the window has no catch frame.
    pub catch_cost: Option<f64>,
    /// Distance of the ball at the catch frame from the clip's, both
    /// relative to the root, m (with `catch_cost`).
    pub catch_err: Option<f64>,
    /// The SM reward of the replay over the window and
    /// [`PushConfig::sm_frames`] frames after it (from `skillaug
    /// check-ball`'s search; `None` where not scored, as in the warm
    /// start's [`push_offsets`]).
    pub sm: Option<SmScore>,
    /// Largest absolute offset, rad.
    pub max_offset: f64,
    /// Root mean square of the offset over its axes, rad.
    pub rms_offset: f64,
    /// The offset, rad: three exp-map components per searched joint, in
    /// the order of [`push_joints`] (all zero when no draw beat the
    /// clip's own targets).
    pub offset: Vec<f32>,
}

/// One push window of one clip: the clip's ball, the PD replay of its own
/// targets, and the best offsets on the arms and on the upper body.
#[derive(Clone, Debug)]
pub struct PushFit {
    /// Clip index in the library.
    pub clip: usize,
    /// The window.
    pub window: PushWindow,
    /// The clip's ball velocity at the release, m/s.
    pub vel_ref: [f64; 3],
    /// The clip's own targets (zero offset).
    pub replay: PushSearch,
    /// The clip's own targets with its joint velocities as the drives'
    /// target velocities ([`World::apply_action_with_rates`]: the
    /// `train.velocity_feed_forward` control); not SM-scored (`sm` None).
    pub replay_rates: PushSearch,
    /// Best offset on the arm joints.
    pub arms: PushSearch,
    /// Best offset on the upper-body joints.
    pub upper: PushSearch,
}

fn summary(o: &Outcome, offset: &[f32]) -> PushSearch {
    let n = offset.len().max(1) as f64;
    PushSearch {
        vel: o.vel,
        cost: o.cost,
        catch_cost: o.catch_cost,
        catch_err: o.catch_err,
        sm: o.sm,
        max_offset: offset.iter().fold(0f64, |m, x| m.max(x.abs() as f64)),
        rms_offset: (offset.iter().map(|x| (*x as f64).powi(2)).sum::<f64>() / n).sqrt(),
        offset: offset.to_vec(),
    }
}

/// Cross-entropy search of one window over `joints` (module doc), starting
/// from the zero offset's outcome `replayed`, minimising
/// [`PushConfig::objective`]'s cost (the SM objective needs `scorer`, and
/// `replayed` scored with it). Each draw replays in its own world (rayon);
/// draws are made in order from `rng` before they run, so the result does
/// not depend on the thread count. With a scorer, the best offset's
/// summary carries its SM score; where the window has a catch frame, its
/// cost there.
#[allow(clippy::too_many_arguments)]
fn search(
    make: &(dyn Fn() -> Result<World> + Sync),
    f: &ClipFrames,
    w: PushWindow,
    joints: &[usize],
    cfg: &PushConfig,
    replayed: &Outcome,
    scorer: Option<&Scorer>,
    rng: &mut ChaCha8Rng,
) -> Result<PushSearch> {
    let objective = cfg.objective;
    // the ball objective's draws end at the release, the catch objective's
    // at the catch frame; the SM objective scores each
    let during = scorer.filter(|_| objective == PushObjective::Sm);
    let catching = objective == PushObjective::Catch;
    let d = joints.len() * 3;
    let mut best = (replayed.clone(), vec![0f32; d]);
    let mut mu = vec![0f64; d];
    let mut sd = vec![cfg.init_sd; d];
    for _ in 0..cfg.iterations {
        let draws: Vec<Vec<f32>> = (0..cfg.population)
            .map(|_| {
                (0..d)
                    .map(|k| (mu[k] + sd[k] * crate::random::normal_pair(rng).0) as f32)
                    .collect()
            })
            .collect();
        let mut scored = draws
            .into_par_iter()
            .map(|x| {
                Ok((
                    replay(&mut make()?, f, w, joints, &x, false, during, catching)?,
                    x,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        scored.sort_by(|a, b| a.0.key(objective).total_cmp(&b.0.key(objective)));
        let elites = &scored[..cfg.elites];
        for k in 0..d {
            let m = elites.iter().map(|e| e.1[k] as f64).sum::<f64>() / cfg.elites as f64;
            let v = elites
                .iter()
                .map(|e| (e.1[k] as f64 - m).powi(2))
                .sum::<f64>()
                / cfg.elites as f64;
            mu[k] = m;
            // a floor keeps the search from collapsing onto one draw
            sd[k] = v.sqrt().max(0.01);
        }
        if scored[0].0.key(objective) < best.0.key(objective) {
            best = scored.swap_remove(0);
        }
    }
    if (scorer.is_some() && best.0.sm.is_none())
        || (w.catch.is_some() && best.0.catch_cost.is_none())
    {
        // the best offset, scored once by what its objective did not score
        let again = replay(&mut make()?, f, w, joints, &best.1, false, scorer, true)?;
        best.0.sm = best.0.sm.or(again.sm);
        best.0.catch_cost = again.catch_cost;
        best.0.catch_err = again.catch_err;
    }
    Ok(summary(&best.0, &best.1))
}

/// [`PushFit`] of every push window of clip `clip` (objects `objects`,
/// object 0 a ball), searched with `cfg` and a generator seeded by `seed`,
/// the clip and the window. `model`, `objects` and `opts` are the physics
/// as given: `cfg.physics` is applied by [`fit_pushes`], not here.
///
/// # Errors
/// A world that cannot be built or a frame it refuses.
pub fn fit_pushes_of_clip(
    lib: &MotionLib,
    clip: usize,
    model: &Model,
    objects: &[ObjectSpec],
    opts: &SimOptions,
    cfg: &PushConfig,
    seed: u64,
) -> Result<Vec<PushFit>> {
    let f = &lib.frames[clip];
    let hand = hand_bodies(model);
    let make = || World::new(model, objects, opts);
    let (arms, upper) = (push_joints(model, false), push_joints(model, true));
    let scorer = Scorer::of(lib, cfg);
    let mut out = Vec::new();
    for w in push_windows(f, &hand, cfg.hand_radius, cfg.min_frames) {
        let mut rng = window_rng(seed, clip, w);
        let mut fit = || -> Result<PushFit> {
            let r = f.state(w.release).context("release frame not valid")?;
            let zero = vec![0f32; arms.len() * 3];
            let sc = Some(&scorer);
            let replayed = replay(&mut make()?, f, w, &arms, &zero, false, sc, true)?;
            // its release velocity is all the table shows of it
            let with_rates = replay(&mut make()?, f, w, &arms, &zero, true, None, false)?;
            Ok(PushFit {
                clip,
                window: w,
                vel_ref: std::array::from_fn(|k| r.obj_linvel[k] as f64),
                replay: summary(&replayed, &zero),
                replay_rates: summary(&with_rates, &zero),
                arms: search(&make, f, w, &arms, cfg, &replayed, sc, &mut rng)?,
                upper: search(&make, f, w, &upper, cfg, &replayed, sc, &mut rng)?,
            })
        };
        out.push(fit().with_context(|| format!("frames {}..{}", w.start, w.release))?);
    }
    Ok(out)
}

/// The search's generator for window `w` of clip `clip`.
fn window_rng(seed: u64, clip: usize, w: PushWindow) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ ((clip as u64) << 32) ^ ((w.start as u64) << 16))
}

/// A push window's best offset, for the warm start or the feed-forward
/// targets (`train.warm_start_push`, `train.push_feed_forward`,
/// [`push_offsets`]).
#[derive(Clone, Debug)]
pub struct PushOffset {
    /// Clip index in the library.
    pub clip: usize,
    /// The window: its frames `start..release` get the offset.
    pub window: PushWindow,
    /// Offset of every joint, rad, `[J*3]` exp-map components (zero off
    /// the searched joints).
    pub offset: Vec<f32>,
    /// The ball at the release (and at the catch frame) under the clip's
    /// own targets (zero offset).
    pub own: PushSearch,
    /// The ball at the release (and at the catch frame) under the offset.
    pub found: PushSearch,
    /// The clip's ball velocity at the release, m/s.
    pub vel_ref: [f64; 3],
}

/// The physics a push search replays in: the humanoid, the objects
/// (object 0 the ball) and the simulation options.
#[derive(Clone, Copy)]
pub struct Scene<'a> {
    /// The humanoid.
    pub model: &'a Model,
    /// The objects.
    pub objects: &'a [ObjectSpec],
    /// Simulation options.
    pub opts: &'a SimOptions,
}

/// Best offsets of every push window of `clips` (object 0 a ball;
/// nothing for clips without one), searched as [`fit_pushes_of_clip`] does
/// over the arms or, with `upper`, the whole upper body, and spread onto
/// all `J` joints. The arms' offsets are those of `skillaug check-ball`'s
/// table (same generator); the upper body's are drawn from the start of
/// the window's generator, not after the arms' search as there.
///
/// # Errors
/// A world that cannot be built or a frame it refuses, naming the clip
/// and the window.
pub fn push_offsets(
    lib: &MotionLib,
    clips: &[usize],
    scene: Scene<'_>,
    cfg: &PushConfig,
    upper: bool,
    seed: u64,
) -> Result<Vec<PushOffset>> {
    let Scene {
        model,
        objects,
        opts,
    } = scene;
    if objects.first().is_none_or(|o| o.name != "ball") {
        return Ok(Vec::new());
    }
    let hand = hand_bodies(model);
    let make = || World::new(model, objects, opts);
    let joints = push_joints(model, upper);
    let n_joints = model.bodies.len() - 1;
    let mut out = Vec::new();
    for &clip in clips {
        let f = &lib.frames[clip];
        for w in push_windows(f, &hand, cfg.hand_radius, cfg.min_frames) {
            let mut rng = window_rng(seed, clip, w);
            let mut found = || -> Result<PushOffset> {
                let r = f.state(w.release).context("release frame not valid")?;
                let zero = vec![0f32; joints.len() * 3];
                let scorer = (cfg.objective == PushObjective::Sm).then(|| Scorer::of(lib, cfg));
                let sc = scorer.as_ref();
                let replayed = replay(&mut make()?, f, w, &joints, &zero, false, sc, true)?;
                let found = search(&make, f, w, &joints, cfg, &replayed, sc, &mut rng)?;
                let mut offset = vec![0f32; n_joints * 3];
                for (k, &j) in joints.iter().enumerate() {
                    offset[j * 3..j * 3 + 3].copy_from_slice(&found.offset[k * 3..k * 3 + 3]);
                }
                Ok(PushOffset {
                    clip,
                    window: w,
                    offset,
                    own: summary(&replayed, &zero),
                    found,
                    vel_ref: std::array::from_fn(|k| r.obj_linvel[k] as f64),
                })
            };
            out.push(found().with_context(|| {
                format!(
                    "push search of clip {} ({}), frames {}..{}",
                    clip, lib.clips[clip].name, w.start, w.release
                )
            })?);
        }
    }
    Ok(out)
}

/// [`fit_pushes_of_clip`] for every clip of `lib` whose object 0 is the
/// ball (objects from `root`), under `cfg.physics`.
///
/// # Errors
/// As [`fit_pushes_of_clip`], naming the clip; an object that cannot be
/// loaded.
pub fn fit_pushes(
    lib: &MotionLib,
    model: &Model,
    root: &Path,
    cfg: &PushConfig,
    seed: u64,
) -> Result<Vec<PushFit>> {
    let model = &cfg.physics.model(model);
    let per_clip =
        super::checks::per_clip_with_objects(lib, root, &cfg.physics, |c, objs, opts| {
            if objs.first().is_none_or(|o| o.name != "ball") {
                return Ok(None);
            }
            fit_pushes_of_clip(lib, c, model, objs, opts, cfg, seed).map(Some)
        })?;
    Ok(per_clip.into_iter().flat_map(|(_, v)| v).collect())
}
