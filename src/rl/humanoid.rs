//! The imitation environment of `skillaug train`: N rapier3d humanoids, each
//! tracking a reference trajectory drawn from the motion library (plain
//! reference state initialisation, ε-NSI, or State Transition Field and
//! Stitched Trajectory Graph samples, with Adaptive Trajectory Sampling).
//!
//! Followed, with sources:
//! - Observation: as Ingrid789/SkillMimic-V2 builds it
//!   (`skillmimic/env/tasks/humanoid_task.py`, `humanoid_object_task.py`,
//!   `skillmimic1.py` for the condition, `skillmimic1_hist.py` for the history;
//!   [`obs_dim`], [`write_observation`]): root height; bodies 1.. relative to
//!   the root, tan-norm rotations, linear and angular velocities of every body,
//!   all in the heading frame; raw world-frame net contact forces on the ten
//!   fingertips; per object its heading-frame xy offset with absolute height,
//!   tan-norm rotation, linear and angular velocity; a 64-slot one-hot of the
//!   skill class; optionally the 3-D history embedding of the frozen encoder
//!   (`skillmimic1_hist.py`: computed from the 60 feature frames *before* the
//!   current one is appended; at a reset the history is the reference clip's
//!   frames before the start frame). Options, off by default: the next
//!   reference frame relative to the character ([`write_reference_obs`],
//!   before the embedding), and residual actions around the next reference
//!   pose ([`EnvConfig::residual_action`]); docs/training.md has what they
//!   measured.
//! - Reward: the paper's timing r_t = S(s_{t+1}, ŝ_{t+1}) (Eq. 12 with the
//!   post-step state against the next reference frame), not the reference
//!   code's one-step lag (`_hook_post_step` in `skillmimic1.py`). SM
//!   (Eqs. 12–17) or DM (Eq. 18) from [`crate::reward`]; classes 0 and 10 (no
//!   object) use the body factor only
//!   (`skillmimic/utils/motion_data_handler.py`). The SM reward is computed for
//!   every method too, as the common yardstick of the training metrics.
//! - Masked steps (inserted states s∅ and missing reference frames) carry no
//!   reward of their own: by default their reward is the mean reward, at the
//!   same step, of the unmasked environments tracking the same clip (else of
//!   all unmasked ones, else 0), the reference code's rule
//!   (`skillmimic1_rand.py`), so they neither reward nor punish the value
//!   estimate; `train.masked_reward = "zero"` gives 0 instead. They are left out of
//!   the reported mean rewards.
//! - Episodes: at most T = `train.episode_length` policy steps (60); a fall (root below
//!   0.3 m after the first step, or a per-skill height) terminates except for
//!   class 0 (Getup) (`humanoid_task.py`, `skillmimic1_unified.py`); so does a
//!   tracking failure when its thresholds are set ([`tracking_lost`]: mean
//!   key-point distance to the reference, ball too far from the root or
//!   from the reference's ball); a
//!   reward-collapse termination is an option (off by default); timeouts are
//!   truncations, bootstrapped by the trainer (as
//!   `skillmimic/learning/common_agent.py` does). With `continue_steps` a
//!   reference that reaches its clip's end continues from the clip's seam
//!   ([`crate::augment::seam`]), anchored to where the character is, so the
//!   episode runs its full length (the reference code stops at the clip's end);
//!   `seam_blend_steps` blends the first frames after a seam
//!   ([`crate::augment::seam::blend`]).
//! - Contacts are read after every physics substep of a policy step
//!   ([`World::step_with_contacts`]); the ball-hands edge of the reward
//!   follows [`crate::reward::ContactDetect`].
//! - Starts: [`StfSampler`] with the trainer's `p_e`/`p_n`. A start that is a
//!   reference frame itself (β = 1) is followed by the next frame
//!   ŝ_{j+1}: the paper's reward timing (Eq. 7 read literally would ask the
//!   first step to stay at ŝ_j). ε-NSI without STF follows the centroid's
//!   clip from the next frame with no connection and no masked state.
//! - Classes 0 and 10 in a world with a ball: the ball is parked 10 m away at
//!   rest (the reference code throws it to a random place,
//!   `motion_data_handler.py`).
//!
//! Every episode runs in a freshly built world, so an episode depends only
//! on its start and its actions: [`HumanoidEnv::snapshot`] and
//! [`HumanoidEnv::restore`] rebuild the running episodes exactly from those
//! (the trainer's checkpoints).

use super::{StepResult, VecEnv};
use crate::augment::ats::{Ats, AtsParams, AtsWeights, Update};
use crate::augment::seam::{Seam, SeamMatch, SeamPool};
use crate::augment::stf::{StartKind, Step, StfParams, StfSampler, Trajectory};
use crate::motion::{quat, MotionLib, Skeleton, State};
use crate::nn::he::{self, HistoryEncoder};
use crate::nn::he_kernel::{EncoderCache, EncoderKernel};
use crate::reward::{self, DatasetKind, RewardOptions, Weights};
use crate::sim::mjcf::Model;
use crate::sim::world::{rotation_of, vector_of, Spring, GRAVITY};
use crate::sim::{ContactReport, ObjectSpec, SimOptions, World};
use anyhow::{bail, ensure, Context, Result};
use rand_chacha::ChaCha8Rng;
use rapier3d::math::{Rotation, Vector};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Slots of the skill condition (one-hot of the class id).
pub use crate::motion::library::CONDITION_SLOTS;

/// Which imitation reward trains the policy (also `--method` of `skillaug
/// train`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// SkillMimic's multiplicative reward (Eqs. 12–17).
    #[default]
    #[value(help = "SkillMimic's multiplicative reward")]
    Sm,
    /// DeepMimic's additive reward (Eq. 18).
    #[value(help = "DeepMimic's additive reward")]
    Dm,
}

/// The reward of a masked step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskedReward {
    /// Mean of the unmasked environments on the same clip at this step (the
    /// reference code's rule, Ingrid789/SkillMimic-V2
    /// `skillmimic/env/tasks/skillmimic1_rand.py`).
    #[default]
    ClipMean,
    /// Zero.
    Zero,
}

/// Environment settings.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvConfig {
    /// Training reward.
    pub method: Method,
    /// End an episode when the root falls below `fall_height`.
    pub early_termination: bool,
    /// Fall threshold, m (0.3).
    pub fall_height: f32,
    /// End an episode when an unmasked step's SM reward is below this (0 = off).
    pub collapse_reward: f64,
    /// Reward of masked steps.
    pub masked_reward: MaskedReward,
    /// SM reward options.
    pub reward: RewardOptions,
    /// ε-NSI baseline: noised starts follow their centroid's clip (no
    /// connection rule, no masked states).
    pub nsi_follow: bool,
    /// ATS on (weights from the rollouts' rewards) or off (uniform).
    pub ats: bool,
    /// ATS exponents.
    pub ats_params: AtsParams,
    /// ATS statistic update.
    pub ats_update: Update,
    /// Condition shown to the policy instead of the skill's own class
    /// (evaluation of skill transitions).
    pub condition: Option<u32>,
    /// Episodes last exactly this many steps instead of to the end of
    /// their reference (evaluation trials).
    pub fixed_length: Option<usize>,
    /// ParaHome's object-centric test perturbation of the start: object
    /// turned about the vertical by U[-45°, 45°] and moved by up to 10 cm
    /// horizontally (paper Section 5; in Ingrid789/SkillMimic-V2 only as
    /// commented-out code, `skillmimic/env/tasks/skillmimic_parahome.py`).
    pub object_perturb: bool,
    /// Continue a reference that reaches its clip's last valid frame from
    /// the clip's seam ([`crate::augment::seam`]) until the episode has
    /// `continue_steps` policy steps (0 = stop at the clip's end, the
    /// reference code's rule, Ingrid789/SkillMimic-V2
    /// `skillmimic/env/tasks/humanoid_task.py`).
    pub continue_steps: usize,
    /// End an episode when the mean distance of the 18 key points (root
    /// and 17 key bodies) to the reference's exceeds this, m (0 = off).
    pub term_key_distance: f64,
    /// End an episode when object 0 is farther than this from the root
    /// while the reference's is not (a shot's ball may leave), m (0 = off;
    /// classes without an object never).
    pub term_object_distance: f64,
    /// End an episode when object 0 is farther than this from the
    /// reference's object 0 (the continued reference, anchored where the
    /// character is), m (0 = off; only while the step has a reference;
    /// classes without an object never): a ball that keeps near the
    /// character but has left its dribble (rolling at the feet, its bounce
    /// died away) ends the episode too.
    pub term_object_error: f64,
    /// Fall thresholds replacing `fall_height` for some skills, m.
    pub fall_height_by_skill: std::collections::BTreeMap<String, f32>,
    /// Masked steps at a seam at least (Eq. 20 gives N = 0 for every
    /// β > 0.1; 0 = Eq. 20 alone).
    pub seam_masked_min: u32,
    /// Residual actions: the PD targets are π·clamp(a + e/π, −1, 1) with e
    /// the next reference frame's joint exp-maps (the action offsets the
    /// reference pose component by component, as UHC's policy corrects its
    /// reference, Luo et al. 2021, Section 3.2) instead of π·a alone (Eq. 11,
    /// the reference code); targets saturate at ±π rad. The next frame is
    /// the one the episode's reference reaches at the coming step; at a
    /// masked step the last one is kept, at the start of an episode without
    /// one the start's own pose.
    pub residual_action: bool,
    /// Append the next reference frame to the observation
    /// ([`reference_obs_dim`], [`write_reference_obs`]; after the skill
    /// condition, before the history embedding), as tracking controllers
    /// do (DeepMimic's phase, PHC's target state: Luo et al. 2023,
    /// Section 3); off = the skill condition alone (the paper, B.1). During
    /// a seam's masked steps and on the last step of an episode it shows
    /// the last frame known; zeros until an episode has one (a start with
    /// masked steps); the object offsets are zero for classes without an
    /// object.
    pub reference_obs: bool,
    /// Lead of the feed-forward PD targets, in frames (residual actions and
    /// the warm start's targets): e_{t+1} + lead·(e_{t+1} − e_t) instead of
    /// the next frame's joint exp-maps e_{t+1} alone (0), to make up for the
    /// PD controller's lag behind a moving target. Only between consecutive
    /// frames of one clip under one anchor: not across a seam, after masked
    /// steps or at an episode's first step.
    pub feed_forward_lead: f32,
    /// With [`EnvConfig::residual_action`]: also give the PD drives the
    /// next reference frame's joint velocities as target velocities
    /// ([`crate::sim::world::World::apply_action_with_rates`],
    /// [`crate::sim::world::joint_rates`]), so the drives follow the moving
    /// reference without the kd/kp = 0.1 s lag of a zero target velocity;
    /// off = zero target velocities, the reference code's PD control. At a
    /// masked step the last frame's are kept, like its pose.
    pub velocity_feed_forward: bool,
    /// Which joints get the feed-forward target velocities of
    /// [`EnvConfig::velocity_feed_forward`]; the others keep a zero target
    /// velocity (damped, as in the reference code).
    pub velocity_feed_forward_joints: JointSet,
    /// With [`EnvConfig::residual_action`]: factor on the policy's residual
    /// of the joints in [`EnvConfig::residual_scale_joints`], so their PD
    /// targets are π·clamp(f + scale·a, −1, 1) rad, f the feed-forward
    /// action (`Episode::ff`): the feed-forward pose weighs more against
    /// the policy's correction, and the action noise moves those targets
    /// `scale` times as far; 1 = f + a on every joint; 0 = the
    /// feed-forward pose alone on those joints (the trainer then leaves
    /// their action values out of the policy's Gaussian,
    /// [`crate::rl::ppo::PpoConfig::free_dims`]).
    pub residual_scale: f32,
    /// Which joints' residual [`EnvConfig::residual_scale`] scales.
    pub residual_scale_joints: JointSet,
    /// Continued frames blended with the old clip's last frame after a seam
    /// ([`crate::augment::seam::blend`], weights 1/(K+1) .. K/(K+1) on the
    /// new frames); 0 = the reference jumps to the seam frame.
    pub seam_blend_steps: usize,
    /// Policy steps after a seam (the first continued step or the first
    /// masked step of a seam) in which the key-point rule of
    /// [`tracking_lost`] does not end an episode; falls and the object rule
    /// still do. 0 = the rule applies at every step.
    pub term_grace_steps: usize,
    /// Strength of the object assist now (0 = off; the trainer sets it
    /// every iteration from `train.object_assist`, fading to 0; evaluation
    /// never uses it): over each policy step with a reference for its end,
    /// object 0 is pulled towards that reference's object position and
    /// velocity by [`World::pull_object`] at natural frequency
    /// [`OBJECT_ASSIST_HZ`]. Not in the paper or the reference code: a
    /// curriculum that lets the policy meet the dribble's later states
    /// while its pushes are still weaker than the clip's (docs/training.md,
    /// "The clip's own motion does not keep its ball").
    pub object_assist: f32,
    /// Dead band of the object assist, m (0 = none): within this distance
    /// of the reference's object position no force acts; beyond it the
    /// spring pulls towards the nearest point of the band's sphere
    /// ([`World::pull_object`]), so the assist only keeps the ball from
    /// being lost and the reward still scores the push inside the band.
    pub object_assist_band: f32,
    /// What a seam frame is matched to when a continued reference's clip
    /// ends ([`SeamMatch`]): the clip's precomputed seam, or the skill's
    /// frame most similar to the simulated state at that step.
    pub seam_match: SeamMatch,
    /// The reference's clock follows the ball (0 = off, the clip's clock):
    /// after every policy step the reference frame the step is scored
    /// against, and whose successor the next step's feed-forward and
    /// observation show, is the clip's next frame, or the one before it
    /// (the reference waits) when object 0's bounce is more than half a
    /// frame behind that frame's ball ([`ball_phase_lead`]), or the one
    /// after it (the reference runs ahead) when it is more than half a
    /// frame ahead. Only along consecutive frames of one clip under one
    /// anchor, and at most this many frames net between a start or seam
    /// and the next seam; classes without an object keep the clip's clock.
    /// The reference's root still travels by the clip's clock: a wait or a
    /// run ahead moves the whole reference horizontally by the root's
    /// travel over the frame waited or skipped.
    /// A dribble whose bounce comes back low and early then meets the
    /// reference's push when the ball arrives, not at the clip's time
    /// (docs/training.md, "A reference whose clock follows the ball").
    /// Not in the paper or the reference code.
    pub ball_clock_frames: usize,
    /// Probability that a training episode starts from a state a rollout
    /// reached ([`SimStart`]) instead of a draw from the STF sampler
    /// (0 = off: every start is the sampler's). Rollouts leave one such
    /// state every [`SIM_START_EVERY`] policy steps from step
    /// `sim_start_after` of their episode on, at steps with an unmasked
    /// reference frame that a later frame of its clip follows, into a
    /// pool of the last [`SIM_START_POOL`] (per rank); a start draws one
    /// of them uniformly and follows the rest of its clip, continued past
    /// the clip's end as any episode. So PPO sees the later pushes of a
    /// dribble with the ball as the simulation left it (lower than the
    /// clip's after every bounce, docs/training.md), not only the clip's
    /// first push on the clip's ball. Never used in evaluation. Not in the
    /// paper or the reference code.
    pub sim_start_prob: f64,
    /// Policy steps into an episode before its states enter the pool of
    /// [`EnvConfig::sim_start_prob`] (read only when that is > 0).
    pub sim_start_after: usize,
    /// Weight w of the additive ball-energy bonus
    /// ([`crate::reward::energy_bonus`]): at every step with a reference,
    /// of a class with an object, the training reward gains
    /// w exp(-k (E_sim - E_ref)^2) (0 = off). The SM reward that training
    /// and evaluation report is unchanged. Not in the paper or the
    /// reference code.
    pub energy_bonus: f64,
    /// Scale k of that bonus, (kg/J)^2 (read only when `energy_bonus` > 0).
    pub energy_bonus_scale: f64,
    /// Floor ε of the ball's factors in the SM training reward
    /// ([`crate::reward::floored_total`]): at every step of a class with an
    /// object the training reward is r_b (ε + (1 - ε) r_o r_rel r_cg)
    /// (0 = Eq. 12's product). The trainer sets it every iteration from
    /// `train.object_floor`, fading it to 0 when asked. The SM reward that
    /// training and evaluation report is unchanged. Not in the paper or
    /// the reference code.
    pub object_floor: f64,
    /// Push offsets added to the feed-forward PD targets of
    /// [`EnvConfig::residual_action`] (`train.push_feed_forward`): at a
    /// step from an unmasked reference frame `f` of clip `c` to frame
    /// `f + 1` of the same clip under the same anchor, with `f` in a
    /// window's `start..release`, the targets are the next frame's joint
    /// exp-maps plus that window's offset, rad, so the hand pushes as the
    /// push search found it could ([`crate::sim::push::push_offsets`])
    /// before the policy's own part is added (`push_window` in
    /// src/rl/humanoid.rs has the exact rule; with a lead the offset is added to the
    /// extrapolated target, which the replay of the search has not; targets
    /// saturate at ±π rad here as everywhere in training). Masked steps
    /// after a pushed one keep the pose without the offset. Empty = none.
    /// In training and in the policy's evaluation (the offsets travel in
    /// `policy.meta.json`). Not in the paper or the reference code.
    pub push_feed_forward: Vec<PushFeedForward>,
    /// Push windows whose pushing hand follows the simulated ball in the
    /// feed-forward PD targets of [`EnvConfig::residual_action`]
    /// (`train.hand_follows_ball`; empty = off): at a step whose next
    /// reference frame is an unmasked frame `f` of a window's clip within
    /// its blend (`first..=end`), the arm and chest joints of the next
    /// frame's targets are solved ([`crate::sim::hand_path::reach`]) so
    /// that the window's hand body, in the pose rooted at the character's
    /// own root, sits `height` above the simulated ball's centre, moved
    /// further by how the reference ball moves relative to the reference
    /// root from frame `f` to `f + lead`, world axes
    /// ([`crate::sim::hand_path::REACH_LEAD_S`] at the clip's rate; the
    /// lead is shortened to the frames the reference runs on along the
    /// same clip and anchor), weighted by
    /// [`crate::sim::hand_path::BallHand::weight`]. The reference the
    /// reward and the observation use is unchanged. In training and in the
    /// policy's evaluation (the windows are found again from the clips).
    /// Not in the paper or the reference code.
    pub ball_hand: Vec<crate::sim::hand_path::BallHand>,
}

/// One push window's offset for [`EnvConfig::push_feed_forward`].
#[derive(Clone, Debug, PartialEq)]
pub struct PushFeedForward {
    /// Clip index in the library.
    pub clip: usize,
    /// The frames whose step gets the offset: `start..release`
    /// ([`crate::sim::push::PushWindow`]).
    pub frames: std::ops::Range<usize>,
    /// Offset of every joint, rad, `[J*3]` exp-map components.
    pub offset: Vec<f32>,
}

/// Policy steps between two states a rollout leaves for the pool of
/// [`EnvConfig::sim_start_prob`].
pub const SIM_START_EVERY: usize = 10;

/// States the pool of [`EnvConfig::sim_start_prob`] keeps (per rank; the
/// oldest is replaced first).
pub const SIM_START_POOL: usize = 256;

/// Default of [`EnvConfig::sim_start_after`]: 30 policy steps, 1 s at
/// 30 Hz, after the first push of a dribble clip.
pub const SIM_START_AFTER: usize = 30;

/// A state a training rollout reached, kept to start later episodes from
/// ([`EnvConfig::sim_start_prob`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimStart {
    /// Clip of the reference frame the state was scored against.
    pub clip: u32,
    /// That frame; the episode started here follows `frame + 1` on.
    pub frame: u32,
    /// The simulated state, moved rigidly (about the vertical, and
    /// horizontally) so that the reference frame it was scored against
    /// lies where the clip has it: its error to `frame` is the one it had.
    pub state: State,
}

/// How far a ball's bounce is ahead of a reference ball's, s (> 0: the
/// simulated ball is ahead, the reference should run ahead; < 0: it should
/// wait). Each ball is `(z, vz)`: height of its centre, m, and vertical
/// velocity, m/s; `rest`: the centre's height on the floor, m. The phase is
/// read ballistically: a ball is −vz/g seconds past its apex, (vz +
/// √(vz² + 2g(z − rest)))/g from the floor ahead and (−vz + √(…))/g past
/// the floor behind. The lead is the smallest in size of: the gap between
/// the two apex times; the simulated ball's time past the floor plus the
/// reference's to it (the simulated ball has bounced, the reference's not
/// yet); minus the converse. Between bounces a dribbled ball's vertical
/// velocity only falls, so the apex gap orders the phase whatever the
/// heights: a ball that comes back lower than the clip's meets the clip's
/// apex at its own; the two terms across the floor let the reference pass
/// a bounce its ball has not reached (a hand push only speeds the fall,
/// and the lead stays an estimate there).
pub fn ball_phase_lead(sim: (f32, f32), reference: (f32, f32), rest: f32) -> f64 {
    let g = GRAVITY;
    let root = |(z, v): (f32, f32)| {
        let (z, v) = (z as f64, v as f64);
        (v * v + 2.0 * g * (z - rest as f64).max(0.0)).sqrt()
    };
    let to_floor = |b: (f32, f32)| (b.1 as f64 + root(b)) / g;
    let from_floor = |b: (f32, f32)| (-(b.1 as f64) + root(b)) / g;
    let apex = (reference.1 as f64 - sim.1 as f64) / g;
    let bounced = from_floor(sim) + to_floor(reference);
    let waiting = -(to_floor(sim) + from_floor(reference));
    [apex, bounced, waiting]
        .into_iter()
        .fold(f64::INFINITY, |a, b| if b.abs() < a.abs() { b } else { a })
}

/// Object 0's height, m, and vertical velocity, m/s, in frame `f` of a
/// clip (`frames`, at `fps` Hz), as [`ball_phase_lead`] reads a reference
/// ball. The stored velocity is a backward difference (on the frames of a
/// flight that `train.reference_ball = "simulated"` replaced, the
/// simulated ball's own velocity), so on the first
/// frame after a bounce it spans the floor contact and reads far too slow
/// (DF `run`: +2.3 m/s between −5.8 and +4.5), which would make the
/// reference's ball look near its apex; there, when the next frame
/// exists, that frame's velocity plus g/fps (one frame of free flight
/// back) is used instead.
pub fn reference_ball(frames: &crate::motion::ClipFrames, f: usize, fps: f32) -> (f32, f32) {
    let o = 3 * frames.n_objects;
    let vz = |f: usize| frames.obj_linvel[o * f + 2];
    let z = frames.obj_pos[o * f + 2];
    let bounced = f >= 1 && vz(f) > 0.0 && vz(f - 1) < 0.0;
    if bounced && f + 1 < frames.frames && frames.valid[f + 1] {
        (z, vz(f + 1) + (GRAVITY / fps as f64) as f32)
    } else {
        (z, vz(f))
    }
}

/// Natural frequency of the object assist's spring, Hz: at strength 1 the
/// ball closes a gap to its reference within about a fifth of a second
/// (critically damped), and the spring's damping over a held 1/60 s
/// policy step, 2ω·dt = 0.84, stays below the explicit step's limit of 2.
pub const OBJECT_ASSIST_HZ: f32 = 4.0;

impl EnvConfig {
    /// Training defaults for `method` (no evaluation overrides).
    pub fn training(method: Method) -> EnvConfig {
        EnvConfig {
            method,
            early_termination: true,
            fall_height: 0.3,
            collapse_reward: 0.0,
            masked_reward: MaskedReward::ClipMean,
            reward: RewardOptions::default(),
            nsi_follow: false,
            ats: false,
            ats_params: AtsParams::default(),
            ats_update: Update::Mean,
            condition: None,
            fixed_length: None,
            object_perturb: false,
            continue_steps: 0,
            term_key_distance: 0.0,
            term_object_distance: 0.0,
            term_object_error: 0.0,
            fall_height_by_skill: Default::default(),
            seam_masked_min: 0,
            residual_action: false,
            reference_obs: false,
            feed_forward_lead: 0.0,
            velocity_feed_forward: false,
            velocity_feed_forward_joints: JointSet::All,
            residual_scale: 1.0,
            residual_scale_joints: JointSet::All,
            seam_blend_steps: 0,
            term_grace_steps: 0,
            object_assist: 0.0,
            object_assist_band: 0.0,
            seam_match: SeamMatch::Reference,
            ball_clock_frames: 0,
            sim_start_prob: 0.0,
            sim_start_after: SIM_START_AFTER,
            energy_bonus: 0.0,
            energy_bonus_scale: crate::reward::ENERGY_BONUS_SCALE,
            object_floor: 0.0,
            push_feed_forward: Vec::new(),
            ball_hand: Vec::new(),
        }
    }
}

/// Observation size as in Ingrid789/SkillMimic-V2 (902 for BallPlay, 905 with
/// the history embedding: `_setup_character_props` in
/// `skillmimic/env/tasks/humanoid_task.py`, `skillmimic1_hist.py`; ParaHome:
/// `skillmimic/env/tasks/skillmimic_parahome.py`).
pub fn obs_dim(sk: Skeleton, n_objects: usize, he_dim: usize) -> usize {
    let b = sk.n_bodies();
    1 + 3 * (b - 1) + 6 * b + 3 * b + 3 * b + 30 + 15 * n_objects + CONDITION_SLOTS + he_dim
}

/// Size of the reference block of the observation with `n_objects`
/// objects: 63 for BallPlay (see [`write_reference_obs`]).
pub fn reference_obs_dim(n_objects: usize) -> usize {
    1 + 54 + 2 + 3 + 3 * n_objects
}

/// Write the reference block of the observation (length
/// [`reference_obs_dim`]) of a character in state `s` whose next reference
/// frame is `r` (zeros when `None`): the reference's root height (m); its
/// 18 key points (root and 17 key bodies) minus the character's (m); the
/// cosine and sine of its heading minus the character's; its root linear
/// velocity (m/s); each object's reference position minus the simulated
/// one (m). Vectors in the character's heading frame.
pub fn write_reference_obs(s: &State, r: Option<&State>, sk: Skeleton, out: &mut [f32]) {
    out.fill(0.0);
    let Some(r) = r else { return };
    let h = quat::heading(s.root_rot);
    let inv = Rotation::from_rotation_z(-(h as f32));
    let mut i = 0;
    let mut put = |v: &[f32]| {
        out[i..i + v.len()].copy_from_slice(v);
        i += v.len();
    };
    put(&[r.root_pos[2]]);
    let (a, b) = (reward::key_points(s, sk), reward::key_points(r, sk));
    for (pa, pb) in a.chunks_exact(3).zip(b.chunks_exact(3)) {
        let d = Vector::new(
            (pb[0] - pa[0]) as f32,
            (pb[1] - pa[1]) as f32,
            (pb[2] - pa[2]) as f32,
        );
        put(&(inv * d).to_array());
    }
    let dh = quat::wrap_angle(quat::heading(r.root_rot) - h);
    put(&[dh.cos() as f32, dh.sin() as f32]);
    put(&(inv * vector_of(&r.root_linvel)).to_array());
    for (po, ro) in s.obj_pos.chunks_exact(3).zip(r.obj_pos.chunks_exact(3)) {
        put(&(inv * (vector_of(ro) - vector_of(po))).to_array());
    }
}

/// The ten fingertip bodies of the contact observation (contact-obs slots
/// 0..9 = key-body slots 7..16).
pub fn fingertips(sk: Skeleton) -> &'static [usize] {
    &sk.key_bodies()[7..]
}

/// Tangent (rotated x) and normal (rotated z) of `q`.
fn tan_norm(q: Rotation) -> [f32; 6] {
    let t = q * Vector::X;
    let n = q * Vector::Z;
    [t.x, t.y, t.z, n.x, n.y, n.z]
}

/// Write the observation of `w` (in state `s`, after a step that produced
/// `contacts`, or `None` right after a reset) for skill class `class` into
/// `out` (length [`obs_dim`], plus [`reference_obs_dim`] with the
/// reference observation); the slots after the condition (reference block,
/// history embedding) are left at 0.
pub fn write_observation(
    w: &World,
    s: &State,
    contacts: Option<&ContactReport>,
    sk: Skeleton,
    class: u32,
    out: &mut [f32],
) {
    let mut rot = Vec::new();
    let mut angvel = Vec::new();
    w.body_frames(&mut rot, &mut angvel);
    let nb = sk.n_bodies();
    let inv = Rotation::from_rotation_z(-(quat::heading(s.root_rot) as f32));
    let root = vector_of(&s.root_pos);
    out.fill(0.0);
    let mut i = 0;
    let mut put = |v: &[f32]| {
        out[i..i + v.len()].copy_from_slice(v);
        i += v.len();
    };
    put(&[s.root_pos[2]]);
    for b in 1..nb {
        put(&(inv * (vector_of(&s.body_pos[3 * b..]) - root)).to_array());
    }
    for b in 0..nb {
        put(&tan_norm(inv * rotation_of(&rot[4 * b..])));
    }
    for b in 0..nb {
        put(&(inv * vector_of(&s.body_vel[3 * b..])).to_array());
    }
    for b in 0..nb {
        put(&(inv * vector_of(&angvel[3 * b..])).to_array());
    }
    for &f in fingertips(sk) {
        put(&contacts.map_or([0.0; 3], |c| c.body_force[f]));
    }
    for k in 0..w.n_objects() {
        let p = vector_of(&s.obj_pos[3 * k..]);
        let d = inv * (p - root);
        put(&[d.x, d.y, p.z]);
        put(&tan_norm(inv * rotation_of(&s.obj_rot[4 * k..])));
        put(&(inv * vector_of(&s.obj_linvel[3 * k..])).to_array());
        put(&(inv * Vector::from(w.object_angvel_world(k))).to_array());
    }
    // load_library refuses class ids >= CONDITION_SLOTS (motion::library::check_classes).
    let cond = i + class as usize;
    out[cond] = 1.0;
}

/// The frozen history encoder and the standardised features of every
/// reference frame (for the history at a reset).
#[derive(Clone)]
pub struct HeRuntime {
    enc: HistoryEncoder,
    /// The encoder's forward pass one window position at a time, which
    /// the environments use (`crate::nn::he_kernel`).
    kernel: std::sync::Arc<EncoderKernel>,
    feats: Vec<Vec<Option<Vec<f32>>>>,
}

impl HeRuntime {
    /// Wrap a loaded encoder for `lib` (on any device: the environments
    /// run it on the CPU); refuses an encoder built for another skeleton.
    pub fn new(enc: HistoryEncoder, lib: &MotionLib) -> Result<HeRuntime> {
        let cfg = &enc.cfg;
        ensure!(
            cfg.skeleton == lib.skeleton.name(),
            "the history encoder was trained on skeleton `{}`, the clips use `{}`",
            cfg.skeleton,
            lib.skeleton.name()
        );
        let feats = he::clip_features(lib, cfg);
        let kernel = std::sync::Arc::new(EncoderKernel::new(&enc)?);
        Ok(HeRuntime { enc, kernel, feats })
    }

    /// Embedding size.
    pub fn dim(&self) -> usize {
        self.enc.cfg.embedding
    }

    fn k(&self) -> usize {
        self.enc.cfg.history
    }

    fn c(&self) -> usize {
        self.enc.cfg.channels
    }

    /// The standardised feature of a simulated state.
    fn feature(&self, s: &State, sk: Skeleton) -> Vec<f32> {
        he::standardised_feature(s, sk, &self.enc.cfg)
    }

    /// The history before frame `frame` of clip `clip`.
    fn prefill(&self, clip: usize, frame: usize) -> Vec<f32> {
        he::window(&self.feats[clip], frame, self.k(), self.c())
    }

    /// The embedding (`[mu]`) of one `[k*C]` window, reusing and updating
    /// `cache` (the same bits as without it: [`EncoderKernel::encode_cached`]).
    fn encode(&self, window: &[f32], cache: &mut EncoderCache) -> Vec<f32> {
        self.kernel.encode_cached(window, cache).0
    }
}

/// Turn a 3-vector `v` (`[3]`, its x, y) about the vertical by `yaw`, rad.
fn turn_vectors(v: &mut [f32], yaw: f64) {
    let (sn, cs) = yaw.sin_cos();
    let (x, y) = (v[0] as f64, v[1] as f64);
    v[0] = (cs * x - sn * y) as f32;
    v[1] = (sn * x + cs * y) as f32;
}

/// Turn each object about the vertical through its centre by U[-45°, 45°]
/// and move it by a uniform distance up to 10 cm in a uniform direction.
fn perturb_objects(s: &mut State, rng: &mut ChaCha8Rng) {
    use rand::Rng;
    for k in 0..s.obj_pos.len() / 3 {
        let yaw = rng.random_range(-std::f32::consts::FRAC_PI_4..std::f32::consts::FRAC_PI_4);
        let r = 0.1 * rng.random::<f32>();
        let a = rng.random_range(0.0..std::f32::consts::TAU);
        s.obj_pos[3 * k] += r * a.cos();
        s.obj_pos[3 * k + 1] += r * a.sin();
        let q = Rotation::from_rotation_z(yaw) * rotation_of(&s.obj_rot[4 * k..]);
        s.obj_rot[4 * k..4 * k + 4].copy_from_slice(&[q.x, q.y, q.z, q.w]);
    }
}

/// Why [`tracking_lost`] ended an episode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lost {
    /// The key points strayed from the reference's.
    KeyPoints,
    /// The object left the character while the reference kept it.
    Object,
}

/// Whether a simulated state `s` has lost its reference: the mean distance
/// of the 18 key points (root and 17 key bodies) to `reference`'s is above
/// `key_distance` (m; only with a reference, 0 = off), or object 0 is
/// farther than `object_distance` from the root (m; 0 = off) while the
/// reference's object is not (so a shot's flight does not count), or
/// object 0 is farther than `object_error` from the reference's object 0
/// (m; only with a reference, 0 = off).
pub fn tracking_lost(
    s: &State,
    reference: Option<&State>,
    sk: Skeleton,
    key_distance: f64,
    object_distance: f64,
    object_error: f64,
) -> Option<Lost> {
    if key_distance > 0.0 {
        if let Some(r) = reference {
            let (a, b) = (reward::key_points(s, sk), reward::key_points(r, sk));
            let n = a.len() / 3;
            let mean: f64 = a
                .chunks_exact(3)
                .zip(b.chunks_exact(3))
                .map(|(p, q)| {
                    ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
                })
                .sum::<f64>()
                / n.max(1) as f64;
            if mean > key_distance {
                return Some(Lost::KeyPoints);
            }
        }
    }
    if object_distance > 0.0 && s.obj_pos.len() >= 3 {
        let near_in_reference =
            reference.is_none_or(|r| dist3(&r.obj_pos, &r.root_pos) <= object_distance);
        if near_in_reference && dist3(&s.obj_pos, &s.root_pos) > object_distance {
            return Some(Lost::Object);
        }
    }
    if let Some(r) = reference.filter(|r| object_error > 0.0 && r.obj_pos.len() >= 3) {
        if s.obj_pos.len() >= 3 && dist3(&s.obj_pos, &r.obj_pos) > object_error {
            return Some(Lost::Object);
        }
    }
    None
}

/// Distance between the points in the first three values of `a` and `b`,
/// m, the differences taken in f32 and squared and summed in f64.
fn dist3(a: &[f32], b: &[f32]) -> f64 {
    (0..3)
        .map(|i| ((a[i] - b[i]) as f64).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Push `f` as the newest frame of a `[k*C]` history.
fn push_history(hist: &mut [f32], f: &[f32]) {
    let c = f.len();
    hist.copy_within(c.., 0);
    let n = hist.len();
    hist[n - c..].copy_from_slice(f);
}

/// A rigid move about the vertical applied to continued reference frames:
/// [`reward::apply_alignment`]'s (yaw, pivot, to).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Anchor {
    yaw: f64,
    pivot: [f64; 2],
    to: [f64; 2],
}

/// One running episode.
struct Episode {
    traj: Trajectory,
    /// Steps after the trajectory's own, continued past clip ends, each
    /// with the move that anchors its reference frame.
    cont: Vec<(Step, Option<Anchor>)>,
    /// Per continued step: the frame the old clip ended on and the weight
    /// of the new frame, for the steps blended after a seam.
    blend: Vec<Option<(std::sync::Arc<State>, f32)>>,
    /// A seam whose masked steps are running: its frames follow them,
    /// anchored where the character is when they end.
    pending: Option<Seam>,
    /// With `seam_blend_steps`: the reference frame the old clip ended on,
    /// kept through a seam's masked steps for the blend after them.
    pending_from: Option<std::sync::Arc<State>>,
    /// Policy step of the last seam (`None` before the first).
    seam_t: Option<usize>,
    /// Index of the current step in [`Episode::step_at`]'s list: `t`, or
    /// apart from it when the reference's clock follows the ball
    /// ([`EnvConfig::ball_clock_frames`]).
    at: usize,
    /// Frames the reference has run ahead (> 0) or waited (< 0) since the
    /// start or the last seam.
    drift: i64,
    /// Horizontal move, m, added to the reference so that its root travels
    /// by the clip's clock while its frames follow the ball's: each wait
    /// adds the root's travel over the frame it waited, each run ahead
    /// takes away the frame it skipped. A seam's anchor is set less it, so
    /// the seam frame still lands on the character.
    shift: [f64; 2],
    class: u32,
    /// Training-reward weights of this episode (object terms off for classes 0/10).
    weights: Weights,
    /// SM weights of this episode (the metric).
    sm_weights: Weights,
    /// (clip, frame) whose ATS statistic this episode updates.
    ats_key: (usize, usize),
    /// Policy steps taken.
    t: usize,
    /// Object-assist strength of each step (empty while every step had
    /// none; see [`EpisodeRecord::assists`]).
    assists: Vec<f32>,
    /// Floor of the ball's reward factors at each step (empty while every
    /// step had none; see [`EpisodeRecord::floors`]).
    floors: Vec<f64>,
    prev_joint_vel: Vec<f32>,
    /// Sum and count of the unmasked raw rewards (the ATS statistic).
    sum: f64,
    n: usize,
    actions: Vec<f32>,
    hist: Vec<f32>,
    /// The encoder's activations of the last embedded `hist`.
    he_cache: EncoderCache,
    /// With residual actions: the coming step's feed-forward action, the
    /// next reference frame's joint exp-maps / π (`[J*3]`; extrapolated by
    /// a lead, plus a push offset inside a window); empty without.
    ff: Vec<f32>,
    /// When `ff` holds a push offset: the same action without it, which
    /// masked steps after the push keep ([`EnvConfig::push_feed_forward`]);
    /// empty otherwise.
    ff_plain: Vec<f32>,
    /// With [`EnvConfig::velocity_feed_forward`]: the coming step's motor
    /// target velocities, rad/s (`[J*3]`); empty without.
    ff_rates: Vec<f32>,
    /// With the reference observation: the next reference frame (anchored).
    next_ref: Option<State>,
    /// With [`EnvConfig::ball_hand`], when the coming step's reference
    /// frame is inside a push window proper (weight 1): the pushing hand
    /// body and where its targets aim ([`HandAim`]); `None` otherwise.
    hand_target: Option<HandAim>,
}

/// Where the pushing hand's feed-forward targets aim at one step
/// ([`crate::sim::hand_path::reach`]), kept for `eval --record`.
#[derive(Clone, Copy, Debug)]
struct HandAim {
    /// The pushing hand body (model body index).
    body: usize,
    /// The point its targets were solved towards, m, world.
    aimed: [f64; 3],
    /// The simulated root before the step (position, m; rotation x, y,
    /// z, w).
    root: ([f32; 3], [f32; 4]),
    /// Set when the step is recorded (forward kinematics is left off the
    /// training path): where the feed-forward targets put the body (the
    /// solved pose as the drives get it: clamped to ±π, with a push
    /// offset where one applies), and where the targets the step applied
    /// (that plus the policy's residual) put it, m, world, both from
    /// `root`.
    posed_applied: Option<([f64; 3], [f64; 3])>,
}

impl Episode {
    /// Policy steps available: the trajectory's and the continued ones.
    fn policy_steps(&self) -> usize {
        self.traj.policy_steps() + self.cont.len()
    }

    /// Step `t` (0 = the start) and its anchor (`None` in the trajectory's
    /// own steps).
    fn step_at(&self, t: usize) -> Option<(Step, Option<Anchor>)> {
        let own = self.traj.steps.len();
        if t < own {
            Some((self.traj.steps[t], None))
        } else {
            self.cont.get(t - own).copied()
        }
    }
}

/// A running episode as the checkpoint stores it: its trajectory and the
/// actions applied so far.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    /// The sampled trajectory (start and reference steps).
    pub traj: Trajectory,
    /// (clip, frame) of its ATS statistic.
    pub ats_key: (usize, usize),
    /// Actions applied so far, `t * act_dim`.
    pub actions: Vec<f32>,
    /// Object-assist strength of each step so far
    /// ([`EnvConfig::object_assist`]); empty while every step had none,
    /// a missing tail reads as 0.
    pub assists: Vec<f32>,
    /// Floor of the ball's factors in the training reward at each step so
    /// far ([`EnvConfig::object_floor`]), so that a replay scores every
    /// step as it was scored (the episode's reward sum feeds the ATS
    /// table); empty while every step had none, a missing tail reads as 0.
    pub floors: Vec<f64>,
}

/// What the success rules (`crate::eval::rules`) see after one policy step.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Probe {
    /// Root position, m.
    pub root: [f32; 3],
    /// Root linear velocity, m/s.
    pub root_vel: [f32; 3],
    /// Object positions, m.
    pub obj: Vec<[f32; 3]>,
    /// Object linear velocities, m/s.
    pub obj_vel: Vec<[f32; 3]>,
    /// Wrist positions (ParaHome: right, left), m.
    pub wrists: Vec<[f32; 3]>,
}

/// One environment's step as `eval --record` keeps it.
#[derive(Clone, Debug)]
pub struct RecordedStep {
    /// Posture after the step.
    pub posture: crate::motion::state::Posture,
    /// Reference frame (clip, frame) the step was scored against; `None`
    /// for a masked step (no reward target).
    pub reference: Option<(u32, u32)>,
    /// Smallest distance from a hand body's origin (wrist or finger joint)
    /// to object 0's centre over the step's physics substeps, m; `None`
    /// without an object ([`crate::sim::world::ContactReport`]).
    pub hand_ball_distance: Option<f32>,
    /// A hand body's collider touched object 0 at any physics substep of
    /// the step (the `touch` contact rule); `None` without an object.
    pub hand_ball_touch: Option<bool>,
    /// With `train.hand_follows_ball`, at a step whose reference frame is
    /// inside a push window proper: the distance from the pushing hand
    /// body's origin after the step to the point its targets were solved
    /// towards before it, m ([`crate::sim::hand_path::reach`]);
    /// `None` otherwise.
    pub hand_target_distance: Option<f32>,
    /// At the same steps: the point the pushing hand's targets were
    /// solved towards before the step, m, world (above the simulated ball,
    /// led by [`crate::sim::hand_path::REACH_LEAD_S`] of the reference
    /// ball's motion, capped at the window's reach); `None` otherwise.
    pub hand_target: Option<[f32; 3]>,
    /// At the same steps: where the feed-forward targets (the solved pose
    /// as the drives get it) put that body, m, world (forward kinematics
    /// from the simulated root before the step; its distance from
    /// `hand_target` is the solver's residual).
    pub hand_target_posed: Option<[f32; 3]>,
    /// At the same steps: where the targets the step applied (the
    /// feed-forward plus the policy's residual) put that body, from the
    /// same root, m, world.
    pub hand_target_applied: Option<[f32; 3]>,
    /// At the same steps: the pushing hand body's origin after the step,
    /// m, world.
    pub pushing_hand_pos: Option<[f32; 3]>,
}

/// What drives one environment's step: the policy's action (`act_dim`
/// values), the object assist's strength ([`EnvConfig::object_assist`])
/// and the floor of the ball's reward factors ([`EnvConfig::object_floor`]).
struct Control<'a> {
    action: &'a [f32],
    assist: f32,
    floor: f64,
}

/// What one environment reports after a step.
struct Outcome {
    reward: Option<f64>,
    sm: Option<f64>,
    /// The SM factors (body, object, relative, contact) of an unmasked step.
    sm_terms: Option<[f64; 4]>,
    fall: bool,
    collapse: bool,
    /// Tracking failure: key points or the object too far.
    lost: Option<Lost>,
    timeout: bool,
    /// The post-step history feature (empty without an encoder).
    feature: Vec<f32>,
    probe: Probe,
    record: Option<RecordedStep>,
    /// A state for the pool of [`EnvConfig::sim_start_prob`].
    capture: Option<SimStart>,
}

/// Totals of the steps since the last [`HumanoidEnv::take_stats`].
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EnvStats {
    /// Environment steps.
    pub steps: u64,
    /// Masked steps.
    pub masked: u64,
    /// Sum of the unmasked training rewards.
    pub reward_sum: f64,
    /// Sum of the unmasked SM rewards.
    pub sm_sum: f64,
    /// Finished episodes.
    pub episodes: u64,
    /// Of which ended by a fall.
    pub falls: u64,
    /// Of which ended by reward collapse.
    pub collapses: u64,
    /// Of which ended by a tracking failure (key points or object too far).
    pub lost: u64,
    /// Of those, by the object leaving the character.
    pub lost_object: u64,
    /// Sums of the SM factors body, object, relative, contact over the
    /// unmasked steps.
    pub sm_factor_sums: [f64; 4],
    /// Finished episodes whose reference was continued past a clip's end.
    pub continuations: u64,
    /// Sum of their lengths (policy steps).
    pub length_sum: u64,
    /// Starts by kind.
    pub starts: StartCounts,
    /// Sum of the masked-state counts N of the starts.
    pub n_masked_sum: u64,
    /// Starts from states rollouts reached ([`EnvConfig::sim_start_prob`];
    /// not in `starts`).
    #[serde(default)]
    pub sim_starts: u64,
}

impl EnvStats {
    /// Add the totals of `o` (another rank's) to these.
    pub fn add(&mut self, o: &EnvStats) {
        self.steps += o.steps;
        self.masked += o.masked;
        self.reward_sum += o.reward_sum;
        self.sm_sum += o.sm_sum;
        self.episodes += o.episodes;
        self.falls += o.falls;
        self.collapses += o.collapses;
        self.lost += o.lost;
        self.lost_object += o.lost_object;
        for (a, b) in self.sm_factor_sums.iter_mut().zip(o.sm_factor_sums) {
            *a += b;
        }
        self.continuations += o.continuations;
        self.length_sum += o.length_sum;
        self.starts.rsi += o.starts.rsi;
        self.starts.rsi_noised += o.starts.rsi_noised;
        self.starts.stg += o.starts.stg;
        self.starts.stg_noised += o.starts.stg_noised;
        self.n_masked_sum += o.n_masked_sum;
        self.sim_starts += o.sim_starts;
    }

    /// Mean unmasked training reward per step.
    pub fn mean_reward(&self) -> f64 {
        self.reward_sum / (self.steps - self.masked).max(1) as f64
    }

    /// Mean unmasked SM reward per step.
    pub fn mean_sm(&self) -> f64 {
        self.sm_sum / (self.steps - self.masked).max(1) as f64
    }

    /// Mean of SM factor `k` (0 body, 1 object, 2 relative, 3 contact) per
    /// unmasked step.
    pub fn mean_sm_factor(&self, k: usize) -> f64 {
        self.sm_factor_sums[k] / (self.steps - self.masked).max(1) as f64
    }

    /// Fraction of finished episodes ended by a tracking failure.
    pub fn lost_rate(&self) -> f64 {
        self.lost as f64 / self.episodes.max(1) as f64
    }

    /// Fraction of finished episodes ended because the object left.
    pub fn lost_object_rate(&self) -> f64 {
        self.lost_object as f64 / self.episodes.max(1) as f64
    }

    /// Fraction of finished episodes that fell.
    pub fn fall_rate(&self) -> f64 {
        self.falls as f64 / self.episodes.max(1) as f64
    }

    /// Mean length of finished episodes.
    pub fn mean_length(&self) -> f64 {
        self.length_sum as f64 / self.episodes.max(1) as f64
    }

    /// Total starts.
    pub fn start_count(&self) -> u64 {
        self.starts.total()
    }
}

/// Episode starts by kind (reference state initialisation or an STG edge,
/// each with or without epsilon-neighbourhood noise).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StartCounts {
    /// Plain reference states.
    pub rsi: u64,
    /// Reference states with neighbourhood noise.
    pub rsi_noised: u64,
    /// STG edges.
    pub stg: u64,
    /// STG edges with neighbourhood noise.
    pub stg_noised: u64,
}

impl StartCounts {
    /// All starts.
    pub fn total(&self) -> u64 {
        self.rsi + self.rsi_noised + self.stg + self.stg_noised
    }

    /// Fraction from the STG (NaN without starts).
    pub fn stg_frac(&self) -> f64 {
        (self.stg + self.stg_noised) as f64 / self.total() as f64
    }

    /// Fraction with neighbourhood noise (NaN without starts).
    pub fn noised_frac(&self) -> f64 {
        (self.rsi_noised + self.stg_noised) as f64 / self.total() as f64
    }

    /// Count one start.
    pub fn add(&mut self, kind: StartKind, noised: bool) {
        *match (kind, noised) {
            (StartKind::Rsi, false) => &mut self.rsi,
            (StartKind::Rsi, true) => &mut self.rsi_noised,
            (StartKind::Stg, false) => &mut self.stg,
            (StartKind::Stg, true) => &mut self.stg_noised,
        } += 1;
    }
}

/// Immutable context shared by the parallel steps.
struct Ctx<'a> {
    lib: &'a MotionLib,
    sk: Skeleton,
    kind: DatasetKind,
    model: Model,
    objects: Vec<ObjectSpec>,
    sim: SimOptions,
    cfg: EnvConfig,
    obs_dim: usize,
    act_dim: usize,
    /// Wrist bodies (ParaHome: right, left) for the success rules.
    wrists: Vec<usize>,
    /// Seam of every clip (used with `continue_steps`).
    seams: Vec<Option<Seam>>,
    /// The frames a seam may continue at (used with
    /// [`SeamMatch::Simulation`]).
    seam_pool: SeamPool,
    /// STF parameters (Eq. 20 at the seams).
    stf: StfParams,
    /// Per joint (`[J]`): whether it gets feed-forward target velocities
    /// (from [`EnvConfig::velocity_feed_forward_joints`]).
    ff_rate_joints: Vec<bool>,
    /// Per action value (`[J*3]`): the factor on the policy's residual
    /// ([`EnvConfig::residual_scale`] on its joints, 1 elsewhere); empty
    /// when every factor is 1.
    residual_gain: Vec<f32>,
}

/// A set of the humanoid's joints: those that
/// [`EnvConfig::velocity_feed_forward`] drives with the reference's joint
/// velocities (`train.velocity_feed_forward_joints`), those whose action
/// noise is correlated in time (`train.noise_correlation_joints`), or those
/// whose residual [`EnvConfig::residual_scale`] scales
/// (`train.residual_scale_joints`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum JointSet {
    /// Every joint.
    #[default]
    All,
    /// The arms and hands only, by body name: every body whose name holds
    /// `Shoulder`, `Elbow` or `Wrist`, and every body below a wrist
    /// ([`crate::sim::push::push_joints`], [`crate::sim::world::hand_bodies`];
    /// BallPlay: 36 of 52 joints; on ParaHome's skeleton the T4 shoulder
    /// bodies match too). Legs, trunk, neck, head and BallPlay's thorax
    /// (clavicle) bodies are left out: with feed-forward they keep a zero
    /// target velocity, so they damp as in the reference code while the
    /// hands follow the clip's pushes.
    Arms,
    /// The fingers only: every body below a wrist, the wrists themselves
    /// left out ([`crate::sim::world::hand_bodies`] less the bodies whose
    /// name holds `Wrist`; BallPlay: 30 of 52 joints, 90 of the 156
    /// action values).
    Fingers,
}

impl JointSet {
    /// The set's name in the settings: `all`, `arms` or `fingers`.
    pub fn name(self) -> &'static str {
        match self {
            JointSet::All => "all",
            JointSet::Arms => "arms",
            JointSet::Fingers => "fingers",
        }
    }

    /// Per joint of `model` (joint j drives body j + 1): whether it is in
    /// the set.
    pub fn mask(self, model: &Model) -> Vec<bool> {
        let nj = model.bodies.len().saturating_sub(1);
        match self {
            JointSet::All => vec![true; nj],
            JointSet::Arms => {
                let hand = crate::sim::world::hand_bodies(model);
                let mut m: Vec<bool> = (0..nj).map(|j| hand[j + 1]).collect();
                for j in crate::sim::push::push_joints(model, false) {
                    m[j] = true;
                }
                m
            }
            JointSet::Fingers => {
                let hand = crate::sim::world::hand_bodies(model);
                (0..nj)
                    .map(|j| hand[j + 1] && !model.bodies[j + 1].name.contains("Wrist"))
                    .collect()
            }
        }
    }
}

/// The feed-forward target velocities (`[J*3]`, rad/s) of a reference
/// frame with joint exp-maps `joint_rot` and their rates `joint_vel`
/// (`[J*3]`, rad and rad/s): [`crate::sim::world::joint_rates`], zero on
/// every joint j whose `mask[j]` ([`JointSet::mask`]) is false.
pub fn masked_joint_rates(mask: &[bool], joint_rot: &[f32], joint_vel: &[f32]) -> Vec<f32> {
    let mut r = crate::sim::world::joint_rates(joint_rot, joint_vel);
    for (j, on) in mask.iter().enumerate() {
        if !on {
            r[3 * j..3 * j + 3].fill(0.0);
        }
    }
    r
}

impl Ctx<'_> {
    /// [`masked_joint_rates`] with the environment's joints.
    fn ff_rates(&self, joint_rot: &[f32], joint_vel: &[f32]) -> Vec<f32> {
        masked_joint_rates(&self.ff_rate_joints, joint_rot, joint_vel)
    }
}

/// The action whose PD targets are the joint exp-maps `joint_rot`
/// (`[J*3]`, rad): e / π, clipped to the action range [-1, 1].
pub fn feed_forward(joint_rot: &[f32]) -> Vec<f32> {
    joint_rot
        .iter()
        .map(|e| (e / std::f32::consts::PI).clamp(-1.0, 1.0))
        .collect()
}

/// Per action value of the joints in `mask` (`[J]`, joint j owns values
/// 3j..3j+3): `scale`, 1 elsewhere; empty when `scale` is 1
/// ([`EnvConfig::residual_scale`]).
pub fn residual_gain(mask: &[bool], scale: f32) -> Vec<f32> {
    if scale == 1.0 {
        return Vec::new();
    }
    mask.iter()
        .flat_map(|&on| [if on { scale } else { 1.0 }; 3])
        .collect()
}

/// The action a residual policy's step applies (`[J*3]`, the simulator
/// clamps it to [-1, 1] and maps it to π·x rad, [`World::apply_action`]):
/// the feed-forward `ff` plus the policy's action `a` times `gain`
/// ([`residual_gain`]; empty = 1 on every value).
pub fn residual_targets(a: &[f32], ff: &[f32], gain: &[f32]) -> Vec<f32> {
    if gain.is_empty() {
        return a.iter().zip(ff).map(|(a, f)| a + f).collect();
    }
    a.iter()
        .zip(ff)
        .zip(gain)
        .map(|((a, f), g)| g * a + f)
        .collect()
}

/// The joint exp-maps `next + lead·(next − now)` (`[J*3]`, rad): the
/// next frame's, extrapolated by `lead` frames along the step from `now`
/// (see [`EnvConfig::feed_forward_lead`]); `next` itself when `lead` is 0.
pub fn lead_target(now: &[f32], next: &[f32], lead: f32) -> Vec<f32> {
    if lead == 0.0 {
        return next.to_vec();
    }
    next.iter()
        .zip(now)
        .map(|(n, c)| n + lead * (n - c))
        .collect()
}

fn no_object_class(class: u32) -> bool {
    class == 0 || class == 10
}

/// A started episode: its world, its state and its first observation.
type Started = (World, Episode, Vec<f32>);

impl Ctx<'_> {
    fn weights(&self, class: u32) -> (Weights, Weights) {
        let sm = Weights::sm(self.kind);
        let train = self.cfg.reward.weights.apply(match self.cfg.method {
            Method::Sm => sm,
            Method::Dm => Weights::dm(self.kind),
        });
        if no_object_class(class) {
            (train.without_object(), sm.without_object())
        } else {
            (train, sm)
        }
    }

    /// A fresh world in the trajectory's start state, its episode and its
    /// first observation (without the embedding). The history holds the
    /// reference frames before the start; the start's own feature is
    /// returned beside them for the caller to push after the embedding.
    fn start(
        &self,
        traj: Trajectory,
        ats_key: (usize, usize),
        he: Option<&HeRuntime>,
    ) -> Result<(Started, Vec<f32>)> {
        let mut w = World::new(&self.model, &self.objects, &self.sim)?;
        let mut s = traj.start.clone();
        if no_object_class(traj.condition) {
            for k in 0..w.n_objects() {
                let r = s.root_pos;
                s.obj_pos[3 * k..3 * k + 3].copy_from_slice(&[
                    r[0] + 10.0 + 2.0 * k as f32,
                    r[1] + 10.0,
                    0.5,
                ]);
                s.obj_rot[4 * k..4 * k + 4].copy_from_slice(&[0.0, 0.0, 0.0, 1.0]);
                s.obj_linvel[3 * k..3 * k + 3].fill(0.0);
                s.obj_angvel[3 * k..3 * k + 3].fill(0.0);
            }
        }
        w.set_state(&s)?;
        let g = w.get_state();
        let mut row = vec![0f32; self.obs_dim];
        write_observation(&w, &g, None, self.sk, traj.condition, &mut row);
        let class = traj.condition;
        let (weights, sm_weights) = self.weights(class);
        let (hist, feature) = match he {
            Some(h) => {
                let (c, f) = traj.connect;
                (h.prefill(c as usize, f as usize), h.feature(&g, self.sk))
            }
            None => (Vec::new(), Vec::new()),
        };
        let mut ep = Episode {
            cont: Vec::new(),
            blend: Vec::new(),
            pending: None,
            pending_from: None,
            seam_t: None,
            at: 0,
            drift: 0,
            shift: [0.0; 2],
            class,
            weights,
            sm_weights,
            ats_key,
            t: 0,
            assists: Vec::new(),
            floors: Vec::new(),
            prev_joint_vel: g.joint_vel.clone(),
            sum: 0.0,
            n: 0,
            actions: Vec::new(),
            hist,
            he_cache: EncoderCache::default(),
            traj,
            ff: Vec::new(),
            ff_rates: Vec::new(),
            ff_plain: Vec::new(),
            next_ref: None,
            hand_target: None,
        };
        if self.cfg.residual_action {
            ep.ff = feed_forward(&g.joint_rot);
            if self.cfg.velocity_feed_forward {
                ep.ff_rates = self.ff_rates(&g.joint_rot, &g.joint_vel);
            }
        }
        self.update_next(&mut ep, &g);
        self.write_reference_block(&g, &ep, &mut row);
        Ok(((w, ep, row), feature))
    }

    /// Apply `a` to `w`, advance one policy step, score it and write the new
    /// observation (without the embedding) into `out`.
    fn advance(
        &self,
        w: &mut World,
        ep: &mut Episode,
        control: Control<'_>,
        he: Option<&HeRuntime>,
        record: bool,
        out: &mut [f32],
    ) -> Outcome {
        let Control {
            action: a,
            assist,
            floor,
        } = control;
        ep.actions.extend_from_slice(a);
        if self.cfg.residual_action {
            let total = residual_targets(a, &ep.ff, &self.residual_gain);
            if let Some(aim) = ep.hand_target.as_mut().filter(|_| record) {
                aim.posed_applied = Some((
                    self.posed_body(aim.body, aim.root, &ep.ff),
                    self.posed_body(aim.body, aim.root, &total),
                ));
            }
            if self.cfg.velocity_feed_forward {
                w.apply_action_with_rates(&total, &ep.ff_rates);
            } else {
                w.apply_action(&total);
            }
        } else {
            w.apply_action(a);
        }
        if assist != 0.0 || !ep.assists.is_empty() {
            ep.assists.resize(ep.t, 0.0);
            ep.assists.push(assist);
        }
        if floor != 0.0 || !ep.floors.is_empty() {
            ep.floors.resize(ep.t, 0.0);
            ep.floors.push(floor);
        }
        let assisted = assist > 0.0 && w.n_objects() > 0 && !no_object_class(ep.class);
        let pulled = assisted
            .then(|| self.reference(ep, ep.at + 1))
            .flatten()
            .filter(|r| r.obj_pos.len() >= 3)
            .is_some_and(|r| {
                let omega = 2.0 * std::f32::consts::PI * OBJECT_ASSIST_HZ;
                let (p, v) = (&r.obj_pos, &r.obj_linvel);
                let spring = Spring {
                    strength: assist,
                    omega,
                    band: self.cfg.object_assist_band,
                };
                w.pull_object(0, [p[0], p[1], p[2]], [v[0], v[1], v[2]], spring)
            });
        let contacts = w.step_with_contacts();
        if pulled {
            w.release_object(0);
        }
        let s = w.get_state();
        ep.t += 1;
        ep.at += 1;
        self.follow_ball(ep, &s);
        let tracked = ep.step_at(ep.at).filter(|(st, _)| !st.masked);
        let reference = self.reference(ep, ep.at);
        let opts = &self.cfg.reward;
        let (reward, sm, sm_terms) = match &reference {
            Some(r) => {
                let c = contacts.reward_contacts(
                    self.sk.contact_penalty_bodies(),
                    opts.contact_detect,
                    opts.contact_radius,
                );
                let prev = Some(ep.prev_joint_vel.as_slice());
                let e = reward::errors_with(&s, r, self.sk, opts.root_rot);
                let smooth = reward::smoothness_factor(&s, r, opts, prev);
                let terms = reward::sm_terms(&e, smooth, r, &c, &ep.sm_weights, opts);
                let sm = terms.total;
                let train = match self.cfg.method {
                    Method::Sm => {
                        let t = if ep.weights == ep.sm_weights {
                            terms
                        } else {
                            // `train.reward_weights`: the same errors, other weights
                            reward::sm_terms(&e, smooth, r, &c, &ep.weights, opts)
                        };
                        if no_object_class(ep.class) {
                            t.total
                        } else {
                            reward::floored_total(&t, floor)
                        }
                    }
                    Method::Dm => reward::dm_reward(&s, r, self.sk, &ep.weights, opts.root_rot),
                };
                let train = if self.cfg.energy_bonus > 0.0
                    && !no_object_class(ep.class)
                    && !r.obj_pos.is_empty()
                    && !s.obj_pos.is_empty()
                {
                    let k = self.cfg.energy_bonus_scale;
                    train + reward::energy_bonus(&e, self.cfg.energy_bonus, k)
                } else {
                    train
                };
                (
                    Some(train),
                    Some(sm),
                    Some([terms.body, terms.object, terms.rel, terms.cg]),
                )
            }
            None => (None, None, None),
        };
        if let Some(r) = reward {
            ep.sum += r;
            ep.n += 1;
        }
        let fall_height = self
            .cfg
            .fall_height_by_skill
            .get(&ep.traj.target_skill)
            .copied()
            .unwrap_or(self.cfg.fall_height);
        let fall =
            self.cfg.early_termination && ep.class != 0 && ep.t > 1 && s.root_pos[2] < fall_height;
        let collapse = self.cfg.collapse_reward > 0.0
            && ep.t > 1
            && sm.is_some_and(|x| x < self.cfg.collapse_reward);
        let lost = (self.cfg.early_termination && ep.t > 1)
            .then(|| self.lost(&s, reference.as_ref(), ep))
            .flatten();
        let ended = fall || collapse || lost.is_some();
        let capture = (self.cfg.sim_start_prob > 0.0 && !ended)
            .then(|| self.capture(ep, &s))
            .flatten();
        if !ended {
            self.extend(ep, &s);
        }
        // the hand target that drove this step, before the next replaces it
        let aimed = ep.hand_target;
        self.update_next(ep, &s);
        // (a reference that waited for its ball leaves steps over when the
        // episode reaches its length)
        let timeout = match self.cfg.fixed_length {
            Some(n) => ep.t >= n,
            None => {
                let longest = ep.traj.policy_steps().max(self.cfg.continue_steps);
                ep.at >= ep.policy_steps() || ep.t >= longest
            }
        };
        write_observation(w, &s, Some(&contacts), self.sk, ep.class, out);
        self.write_reference_block(&s, ep, out);
        let probe = self.probe(&s);
        let feature = he.map_or_else(Vec::new, |h| h.feature(&s, self.sk));
        let record = record.then(|| RecordedStep {
            posture: s.posture(),
            reference: tracked
                .filter(|_| reference.is_some())
                .and_then(|(st, _)| st.ref_clip.zip(st.ref_frame)),
            hand_ball_distance: contacts.object_hand_distance.first().copied(),
            hand_ball_touch: contacts.object_hands_any.first().copied(),
            hand_target_distance: aimed.map(|a| {
                let q = &s.body_pos[3 * a.body..3 * a.body + 3];
                let d2: f64 = (0..3).map(|k| (q[k] as f64 - a.aimed[k]).powi(2)).sum();
                d2.sqrt() as f32
            }),
            hand_target: aimed.map(|a| a.aimed.map(|v| v as f32)),
            hand_target_posed: aimed
                .and_then(|a| a.posed_applied)
                .map(|(p, _)| p.map(|v| v as f32)),
            hand_target_applied: aimed
                .and_then(|a| a.posed_applied)
                .map(|(_, p)| p.map(|v| v as f32)),
            pushing_hand_pos: aimed.map(|a| std::array::from_fn(|k| s.body_pos[3 * a.body + k])),
        });
        ep.prev_joint_vel = s.joint_vel;
        Outcome {
            reward,
            sm,
            sm_terms,
            fall,
            collapse,
            lost,
            timeout,
            feature,
            probe,
            record,
            capture,
        }
    }

    /// With [`EnvConfig::sim_start_prob`]: `s` as a [`SimStart`] when the
    /// episode is at least `sim_start_after` steps in, on a multiple of
    /// [`SIM_START_EVERY`] after that, its step `ep.at` has an unmasked
    /// reference frame (not blended after a seam) that a later valid frame
    /// of its clip follows. The state is moved by the inverse of the
    /// ball clock's shift and of the step's anchor, so that it relates to
    /// the clip's frame as it related to the reference it was scored
    /// against.
    fn capture(&self, ep: &Episode, s: &State) -> Option<SimStart> {
        let after = self.cfg.sim_start_after;
        if ep.t < after || !(ep.t - after).is_multiple_of(SIM_START_EVERY) {
            return None;
        }
        let (st, anchor) = ep.step_at(ep.at).filter(|(st, _)| !st.masked)?;
        let own = ep.traj.steps.len();
        if ep.at >= own && matches!(ep.blend.get(ep.at - own), Some(Some(_))) {
            return None;
        }
        let (clip, frame) = (st.ref_clip?, st.ref_frame?);
        let last = self.lib.frames.get(clip as usize)?.last_valid()?;
        if frame as usize + 1 > last {
            return None;
        }
        // reference = shift + anchor(frame): undo the shift, then the anchor
        let mut state = if ep.shift == [0.0; 2] {
            s.clone()
        } else {
            reward::apply_alignment(s, 0.0, [0.0; 2], [-ep.shift[0], -ep.shift[1]])
        };
        if let Some(m) = anchor {
            state = reward::apply_alignment(&state, -m.yaw, m.to, m.pivot);
            if matches!(
                self.sim.angvel_frame,
                crate::motion::clip::AngvelFrame::World
            ) {
                // `apply_alignment` keeps body-frame angular velocities;
                // world-frame ones turn with the state
                turn_vectors(&mut state.root_angvel, -m.yaw);
                state
                    .obj_angvel
                    .chunks_exact_mut(3)
                    .for_each(|v| turn_vectors(v, -m.yaw));
            }
        }
        Some(SimStart { clip, frame, state })
    }

    /// With residual actions or the reference observation: take the
    /// reference frame of step `ep.at + 1` when that step has an unmasked
    /// one (else keep the last, without a push offset): its joint
    /// rotations as `ep.ff` (local, so a continued frame's anchor does not
    /// change them; with [`EnvConfig::feed_forward_lead`] extrapolated,
    /// and inside a window of [`EnvConfig::push_feed_forward`] plus its
    /// offset), the anchored state as `ep.next_ref`.
    fn update_next(&self, ep: &mut Episode, s: &State) {
        let (res, obs) = (self.cfg.residual_action, self.cfg.reference_obs);
        ep.hand_target = None;
        if !(res || obs) {
            return;
        }
        if let Some(r) = self.reference(ep, ep.at + 1) {
            if res {
                let lead = self.cfg.feed_forward_lead;
                // a lead only along one clip: never across a seam's jump
                let along = |t: usize| ep.step_at(t).map(|(st, a)| (st.ref_clip, st.ref_frame, a));
                let consecutive = match (along(ep.at), along(ep.at + 1)) {
                    (Some((c0, Some(f0), a0)), Some((c1, Some(f1), a1))) => {
                        c0 == c1 && f1 == f0 + 1 && a0 == a1
                    }
                    _ => false,
                };
                // the current frame is looked up only when a lead uses it
                let now = (lead != 0.0 && consecutive)
                    .then(|| self.reference(ep, ep.at))
                    .flatten();
                let e = match now {
                    Some(now) => lead_target(&now.joint_rot, &r.joint_rot, lead),
                    None => r.joint_rot.clone(),
                };
                let (e, aim) = self.hand_on_ball(ep, s, &r, e);
                ep.ff = feed_forward(&e);
                ep.ff_plain.clear();
                if let Some(p) = self.push_window(ep) {
                    let pushed: Vec<f32> = e.iter().zip(&p.offset).map(|(e, o)| e + o).collect();
                    ep.ff_plain = std::mem::replace(&mut ep.ff, feed_forward(&pushed));
                }
                ep.hand_target = aim.map(|(body, aimed)| HandAim {
                    body,
                    aimed,
                    root: (s.root_pos, s.root_rot),
                    posed_applied: None,
                });
                if self.cfg.velocity_feed_forward {
                    ep.ff_rates = self.ff_rates(&r.joint_rot, &r.joint_vel);
                }
            }
            if obs {
                ep.next_ref = Some(r);
            }
        } else if !ep.ff_plain.is_empty() {
            // masked steps after a pushed one hold the pose, not the push
            ep.ff = std::mem::take(&mut ep.ff_plain);
        }
    }

    /// The feed-forward joint targets `e` (`[J*3]`, rad) for the step to
    /// `next`, the reference of `ep.at + 1`, with the pushing hand put
    /// on `s`'s ball ([`EnvConfig::ball_hand`]); `e` itself outside the
    /// windows or when off; beside them, inside a window proper (weight
    /// 1), the hand body and the point it was solved towards
    /// ([`Episode::hand_target`]).
    fn hand_on_ball(
        &self,
        ep: &Episode,
        s: &State,
        next: &State,
        e: Vec<f32>,
    ) -> (Vec<f32>, Option<(usize, [f64; 3])>) {
        if self.cfg.ball_hand.is_empty() || s.obj_pos.len() < 3 || next.obj_pos.len() < 3 {
            return (e, None);
        }
        let along = |t: usize| {
            ep.step_at(t)
                .filter(|(st, _)| !st.masked)
                .and_then(|(st, a)| Some((st.ref_clip?, st.ref_frame?, a)))
        };
        let Some((c, f, a)) = along(ep.at + 1) else {
            return (e, None);
        };
        let (c, f) = (c as usize, f as usize);
        let Some(hand) = self
            .cfg
            .ball_hand
            .iter()
            .find(|h| h.clip == c && h.first <= f && f <= h.end)
        else {
            return (e, None);
        };
        let fps = self.lib.clips[c].fps as f64;
        let lead = (crate::sim::hand_path::REACH_LEAD_S * fps).round() as usize;
        // the reference `lead` frames on, or as far as it runs along the
        // same clip and anchor
        let ahead = (1..=lead)
            .rev()
            .find(|&k| {
                along(ep.at + 1 + k)
                    .is_some_and(|(c2, f2, a2)| c2 as usize == c && f2 as usize == f + k && a2 == a)
            })
            .and_then(|k| self.reference(ep, ep.at + 1 + k));
        // the reference ball's displacement relative to the reference's
        // root: the lead that the drives' lag asks of the hand, the
        // character's own travel left out
        let rel = |r: &State| -> [f64; 3] {
            std::array::from_fn(|k| (r.obj_pos[k] - r.root_pos[k]) as f64)
        };
        let disp: [f64; 3] = match &ahead {
            Some(r) if r.obj_pos.len() >= 3 => {
                let (a, b) = (rel(r), rel(next));
                std::array::from_fn(|k| a[k] - b[k])
            }
            _ => [0.0; 3],
        };
        let ball = [s.obj_pos[0], s.obj_pos[1], s.obj_pos[2]].map(|v| v as f64);
        let target = [
            ball[0] + disp[0],
            ball[1] + disp[1],
            ball[2] + hand.height + disp[2],
        ];
        let root = s.root_pos;
        let weight = hand.weight(f);
        let (e, aimed) =
            crate::sim::hand_path::reach(&self.model, hand, root, s.root_rot, &e, target, weight);
        // the point is recorded only inside the window proper
        (e, (weight >= 1.0).then_some((hand.body, aimed)))
    }

    /// Where the PD targets of `action` (`[J*3]`, as
    /// [`World::apply_action`] maps it: π·clamp(x, −1, 1) rad,
    /// [`crate::sim::world::pd_target`]) put `body`, m, world, in a pose
    /// rooted at `root` (position, m; rotation x, y, z, w): forward
    /// kinematics ([`crate::sim::hand_path::body_position`]).
    fn posed_body(&self, body: usize, root: ([f32; 3], [f32; 4]), action: &[f32]) -> [f64; 3] {
        let e: Vec<f32> = action
            .iter()
            .map(|&a| crate::sim::world::pd_target(a))
            .collect();
        crate::sim::hand_path::body_position(&self.model, root.0, root.1, &e, body)
    }

    /// The window of [`EnvConfig::push_feed_forward`] whose offset the
    /// coming step (`ep.at` -> `ep.at + 1`) adds: the step leaves an
    /// unmasked frame f of clip c for frame f + 1 of the same clip under
    /// the same anchor, with f in the window's frames. At an episode's
    /// first step the frame left is the start's own, when the start is
    /// that clip frame itself (a reference start, not drawn from its
    /// neighbourhood, not a rollout's state, without masked steps), as
    /// the push search replays from the window's first frame
    /// ([`crate::sim::push::push_offsets`]).
    fn push_window(&self, ep: &Episode) -> Option<&PushFeedForward> {
        if self.cfg.push_feed_forward.is_empty() {
            return None;
        }
        let along = |t: usize| {
            ep.step_at(t)
                .filter(|(st, _)| !st.masked)
                .and_then(|(st, a)| Some((st.ref_clip?, st.ref_frame?, a)))
        };
        let (c1, f1, a1) = along(ep.at + 1)?;
        let (c, f) = if ep.at == 0 {
            let t = &ep.traj;
            let plain = t.start_kind == StartKind::Rsi
                && !t.noised
                && !t.simulated
                && t.n_masked == 0
                && a1.is_none();
            if !plain {
                return None;
            }
            t.connect
        } else {
            let (c0, f0, a0) = along(ep.at)?;
            if a0 != a1 {
                return None;
            }
            (c0, f0)
        };
        if c != c1 || f1 != f + 1 {
            return None;
        }
        self.cfg
            .push_feed_forward
            .iter()
            .find(|p| p.clip == c as usize && p.frames.contains(&(f as usize)))
    }

    /// Fill the reference block of the observation row `out` (after the
    /// condition, before the history embedding) when it is on.
    fn write_reference_block(&self, s: &State, ep: &Episode, out: &mut [f32]) {
        if !self.cfg.reference_obs {
            return;
        }
        let k = self.objects.len();
        let base = obs_dim(self.sk, k, 0);
        let block = &mut out[base..base + reference_obs_dim(k)];
        write_reference_obs(s, ep.next_ref.as_ref(), self.sk, block);
        if no_object_class(ep.class) {
            // the ball is parked out of play: no offset to show
            block[reference_obs_dim(0)..].fill(0.0);
        }
    }

    /// The reference state of `ep`'s step `t` (anchored when continued,
    /// moved by the ball clock's shift, [`Episode::shift`]); `None` for a
    /// masked step.
    fn reference(&self, ep: &Episode, t: usize) -> Option<State> {
        let (st, anchor) = ep.step_at(t).filter(|(st, _)| !st.masked)?;
        let r = self
            .lib
            .state(st.ref_clip? as usize, st.ref_frame? as usize)?;
        let r = match anchor {
            Some(m) => reward::apply_alignment(&r, m.yaw, m.pivot, m.to),
            None => r,
        };
        let own = ep.traj.steps.len();
        let r = match t.checked_sub(own).and_then(|i| ep.blend.get(i)) {
            Some(Some((from, w))) => crate::augment::seam::blend(from, &r, *w),
            _ => r,
        };
        Some(if ep.shift == [0.0; 2] {
            r
        } else {
            reward::apply_alignment(&r, 0.0, [0.0; 2], ep.shift)
        })
    }

    /// Whether `s` has lost its reference ([`tracking_lost`] with the
    /// episode's thresholds; objects count only for classes with one).
    fn lost(&self, s: &State, reference: Option<&State>, ep: &Episode) -> Option<Lost> {
        let c = &self.cfg;
        let (obj, obj_err) = if no_object_class(ep.class) {
            (0.0, 0.0)
        } else {
            (c.term_object_distance, c.term_object_error)
        };
        let graced = c.term_grace_steps > 0
            && ep
                .seam_t
                .is_some_and(|t| ep.t.saturating_sub(t) <= c.term_grace_steps);
        let key = if graced { 0.0 } else { c.term_key_distance };
        tracking_lost(s, reference, self.sk, key, obj, obj_err)
    }

    /// With [`EnvConfig::ball_clock_frames`]: after a step that moved
    /// `ep.at` to the next entry, move it back one (the reference waits) or
    /// on one (it runs ahead) by the simulated ball's phase lead over that
    /// frame's ([`ball_phase_lead`] of [`reference_ball`], the raw clip
    /// frame: the anchor and a seam's blend change neither height nor
    /// vertical velocity).
    fn follow_ball(&self, ep: &mut Episode, s: &State) {
        let most = self.cfg.ball_clock_frames as i64;
        if most == 0 || no_object_class(ep.class) || s.obj_pos.len() < 3 {
            return;
        }
        let frame = |i: usize| {
            let (st, a) = ep.step_at(i).filter(|(st, _)| !st.masked)?;
            Some((st.ref_clip?, st.ref_frame?, a))
        };
        let Some((c, f, a)) = frame(ep.at) else {
            return;
        };
        // entry `i` holds frame f + df of the same clip under the same anchor
        let along = |i: usize, df: i64| {
            frame(i).is_some_and(|(c2, f2, a2)| c2 == c && a2 == a && f2 as i64 == f as i64 + df)
        };
        let fps = self.lib.clips[c as usize].fps;
        let lead = ball_phase_lead(
            (s.obj_pos[2], s.obj_linvel[2]),
            reference_ball(&self.lib.frames[c as usize], f as usize, fps),
            self.objects
                .first()
                .map_or(0.0, |o| -o.shape.compute_local_aabb().mins.z),
        );
        let half_frame = 0.5 / fps as f64;
        let step = if lead > half_frame && ep.drift < most && along(ep.at + 1, 1) {
            1
        } else if lead < -half_frame && ep.drift > -most && ep.at >= 1 && along(ep.at - 1, -1) {
            -1
        } else {
            0
        };
        if step != 0 {
            let to = (ep.at as i64 + step) as usize;
            let root = |i: usize| {
                self.reference(ep, i)
                    .map(|r| [r.root_pos[0], r.root_pos[1]])
            };
            if let (Some(a), Some(b)) = (root(ep.at), root(to)) {
                ep.shift[0] += (a[0] - b[0]) as f64;
                ep.shift[1] += (a[1] - b[1]) as f64;
            }
            ep.at = to;
            ep.drift += step;
        }
    }

    /// Continue `ep`'s reference past its clip's end (see
    /// [`crate::augment::seam`]) when the step just taken was its last and
    /// the episode may run longer. N = Eq. 20 (β), at least
    /// `seam_masked_min`: with N = 0 the seam frame's successors follow at
    /// once, anchored to `s` (the character's state at the seam); else N
    /// masked steps first, and the seam frame and its successors follow
    /// them, anchored to the character's state when they end (Eq. 7: start,
    /// N masked states, ŝ_j, ŝ_{j+1}, ...).
    fn extend(&self, ep: &mut Episode, s: &State) {
        let total = self.cfg.continue_steps;
        if total == 0 || ep.at < ep.policy_steps() || ep.t >= total {
            return;
        }
        if let Some(seam) = ep.pending.take() {
            let from = ep.pending_from.take();
            self.follow_seam(ep, s, seam, seam.to_frame as usize, from);
            return;
        }
        let Some((last, _)) = ep.step_at(ep.at) else {
            return;
        };
        let Some(clip) = last.ref_clip else { return };
        let own = self.seams.get(clip as usize).copied().flatten();
        let seam = match self.cfg.seam_match {
            SeamMatch::Reference => own,
            // a state no frame connects to (beta <= tau, Eq. 20) continues
            // at the clip's own seam, as with `Reference`
            SeamMatch::Simulation => self
                .seam_pool
                .nearest(self.lib, clip as usize, s, &Weights::sm(self.kind))
                .filter(|x| x.beta > self.stf.tau)
                .or(own),
        };
        let Some(seam) = seam else {
            return;
        };
        let p = &self.stf;
        let Some(n) = crate::augment::n_masked(seam.beta, p.tau, p.n_max, p.mask_rule) else {
            return;
        };
        let n = n.max(self.cfg.seam_masked_min) as usize;
        // the frame the old clip ends on, for a blend after the seam
        let from = (self.cfg.seam_blend_steps > 0)
            .then(|| self.reference(ep, ep.at))
            .flatten()
            .map(std::sync::Arc::new);
        if n == 0 {
            self.follow_seam(ep, s, seam, seam.to_frame as usize + 1, from);
            return;
        }
        let inserted = Step {
            masked: true,
            ref_clip: None,
            ref_frame: None,
        };
        let room = total - ep.t;
        ep.cont
            .extend(std::iter::repeat_n((inserted, None), n.min(room)));
        ep.blend.resize(ep.cont.len(), None);
        ep.pending = Some(seam);
        ep.pending_from = from;
    }

    /// Append the frames of `seam`'s clip from `first` to its last valid
    /// frame (at most to the episode's length), moved so that the seam
    /// frame's root x, y and heading are `s`'s.
    fn follow_seam(
        &self,
        ep: &mut Episode,
        s: &State,
        seam: Seam,
        first: usize,
        from: Option<std::sync::Arc<State>>,
    ) {
        let (c2, j) = (seam.to_clip as usize, seam.to_frame as usize);
        let Some(target) = self.lib.state(c2, j) else {
            return;
        };
        let yaw = quat::wrap_angle(quat::heading(s.root_rot) - quat::heading(target.root_rot));
        let anchor = Anchor {
            yaw,
            pivot: [target.root_pos[0] as f64, target.root_pos[1] as f64],
            // (less the ball clock's shift, which goes on applying)
            to: [
                s.root_pos[0] as f64 - ep.shift[0],
                s.root_pos[1] as f64 - ep.shift[1],
            ],
        };
        let room = self.cfg.continue_steps - ep.t;
        let cf = &self.lib.frames[c2];
        let end = cf.last_valid().unwrap_or(0);
        let steps = (first..=end).take(room).map(|f| {
            (
                Step {
                    masked: !cf.valid[f],
                    ref_clip: Some(c2 as u32),
                    ref_frame: Some(f as u32),
                },
                Some(anchor),
            )
        });
        ep.seam_t = Some(ep.t);
        ep.drift = 0;
        let start = ep.cont.len();
        ep.cont.extend(steps);
        ep.blend.resize(ep.cont.len(), None);
        if let Some(from) = from {
            let k = self.cfg.seam_blend_steps;
            for (i, b) in ep.blend[start..].iter_mut().take(k).enumerate() {
                *b = Some((from.clone(), (i + 1) as f32 / (k + 1) as f32));
            }
        }
    }

    /// What the success rules see of `s`.
    fn probe(&self, s: &State) -> Probe {
        let three = |v: &[f32]| -> Vec<[f32; 3]> {
            v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        };
        Probe {
            root: s.root_pos,
            root_vel: s.root_linvel,
            obj: three(&s.obj_pos),
            obj_vel: three(&s.obj_linvel),
            wrists: self
                .wrists
                .iter()
                .map(|&b| {
                    [
                        s.body_pos[3 * b],
                        s.body_pos[3 * b + 1],
                        s.body_pos[3 * b + 2],
                    ]
                })
                .collect(),
        }
    }
}

/// N humanoid worlds with automatic resets (see the module doc).
pub struct HumanoidEnv<'a> {
    ctx: Ctx<'a>,
    sampler: StfSampler<'a>,
    stf: StfParams,
    ats: Ats,
    ats_weights: AtsWeights,
    worlds: Vec<World>,
    eps: Vec<Episode>,
    obs: Vec<f32>,
    he: Option<HeRuntime>,
    stats: EnvStats,
    /// ATS records since the last [`HumanoidEnv::take_ats_log`]: (clip,
    /// start frame, episode mean reward).
    ats_log: Vec<(usize, usize, f64)>,
    probes: Vec<Probe>,
    sm: Vec<Option<f64>>,
    record: bool,
    records: Vec<Option<RecordedStep>>,
    /// States rollouts reached, to start episodes from
    /// ([`EnvConfig::sim_start_prob`]); at most [`SIM_START_POOL`].
    sim_pool: Vec<SimStart>,
    /// Where the next state goes once the pool is full (the oldest).
    sim_next: usize,
}

/// Everything [`HumanoidEnv::new`] needs.
pub struct EnvParts<'a> {
    /// The motion library.
    pub lib: &'a MotionLib,
    /// Start sampler over it (with the STG edges when `p_e > 0`).
    pub sampler: StfSampler<'a>,
    /// STF parameters (`p_e`, `p_n`, radii, horizon, ...).
    pub stf: StfParams,
    /// The ATS table (clips of skills left out disabled).
    pub ats: Ats,
    /// The humanoid.
    pub model: Model,
    /// Objects of every world.
    pub objects: Vec<ObjectSpec>,
    /// Physics settings.
    pub sim: SimOptions,
    /// Environment settings.
    pub cfg: EnvConfig,
    /// Frozen history encoder (None: no embedding in the observation).
    pub he: Option<HeRuntime>,
    /// Seam of every clip of `lib` ([`crate::augment::seam::seams`]); read
    /// only with `cfg.continue_steps > 0`.
    pub seams: Vec<Option<Seam>>,
    /// The frames a seam may continue at ([`SeamPool::new`]); read only
    /// with `cfg.continue_steps > 0` and [`SeamMatch::Simulation`] (may be
    /// empty otherwise).
    pub seam_pool: SeamPool,
}

impl<'a> HumanoidEnv<'a> {
    /// `n` environments, each started by a draw from `rng`.
    pub fn new(parts: EnvParts<'a>, n: usize, rng: &mut ChaCha8Rng) -> Result<HumanoidEnv<'a>> {
        let lib = parts.lib;
        let sk = lib.skeleton;
        let n_objects = parts.objects.len();
        let he_dim = parts.he.as_ref().map_or(0, HeRuntime::dim);
        if let Some(h) = &parts.he {
            // the feature pads missing objects with zeros (one-object clips
            // beside the two-object clip of ParaHome share one encoder)
            ensure!(
                h.enc.cfg.n_objects >= n_objects,
                "the history encoder was trained with {} object(s); these worlds have {n_objects}",
                h.enc.cfg.n_objects
            );
        }
        ensure!(n > 0, "train: at least one environment is needed");
        crate::motion::library::check_classes(
            lib.clips
                .iter()
                .map(|c| (c.name.as_str(), c.skill.as_str(), c.class as u32)),
        )?;
        let ff_rate_joints = parts.cfg.velocity_feed_forward_joints.mask(&parts.model);
        let residual_gain = residual_gain(
            &parts.cfg.residual_scale_joints.mask(&parts.model),
            parts.cfg.residual_scale,
        );
        let ctx = Ctx {
            lib,
            sk,
            kind: DatasetKind::of_library(lib),
            obs_dim: obs_dim(sk, n_objects, he_dim)
                + if parts.cfg.reference_obs {
                    reference_obs_dim(n_objects)
                } else {
                    0
                },
            act_dim: 3 * sk.n_joints(),
            wrists: ["jRightWrist", "jLeftWrist", "R_Wrist", "L_Wrist"]
                .iter()
                .filter_map(|n| sk.body_names().iter().position(|b| b == n))
                .collect(),
            model: parts.model,
            objects: parts.objects,
            sim: parts.sim,
            cfg: parts.cfg,
            seams: parts.seams,
            seam_pool: parts.seam_pool,
            stf: parts.stf.clone(),
            ff_rate_joints,
            residual_gain,
        };
        let mut env = HumanoidEnv {
            ats_weights: parts.ats.weights(&AtsParams::default()),
            ctx,
            sampler: parts.sampler,
            stf: parts.stf,
            ats: parts.ats,
            worlds: Vec::new(),
            eps: Vec::new(),
            obs: Vec::new(),
            he: parts.he,
            stats: EnvStats::default(),
            ats_log: Vec::new(),
            probes: Vec::new(),
            sm: Vec::new(),
            record: false,
            records: Vec::new(),
            sim_pool: Vec::new(),
            sim_next: 0,
        };
        env.refresh_ats();
        let mut draws = Vec::with_capacity(n);
        for _ in 0..n {
            draws.push(env.draw(rng)?);
        }
        let started = env.start_all(draws)?;
        let od = env.ctx.obs_dim;
        env.obs = vec![0.0; n * od];
        let mut feats = Vec::with_capacity(n);
        for (e, ((w, ep, row), f)) in started.into_iter().enumerate() {
            env.obs[e * od..(e + 1) * od].copy_from_slice(&row);
            env.worlds.push(w);
            env.eps.push(ep);
            feats.push((e, f));
        }
        env.embed_and_push(&feats)?;
        Ok(env)
    }

    /// Behaviour-cloning data for a warm start of the policy mean: for
    /// every frame f of `clips` that can start an episode (valid, in
    /// [2, F - 2]) and whose next frame is valid, the observation of the
    /// reference state ŝ_f set into a fresh world (with the history
    /// embedding of the frames before it), plus `copies` observations of
    /// states drawn from its ε-neighbourhood (the STF radii of the clip's
    /// class, [`crate::augment::stf::perturb`], bodies by forward
    /// kinematics); the target of each is the action whose PD targets are
    /// the joint rotations of ŝ_{f+1} (a = e / π, clamped to [-1, 1]; the
    /// simulator maps a to π a, [`World::apply_action`]; extrapolated by
    /// [`EnvConfig::feed_forward_lead`]), or zero with
    /// [`EnvConfig::residual_action`] (the feed-forward part already holds
    /// ŝ_{f+1}). A frame inside a window of `pushes` (frames
    /// `start..release` of its clip) adds that window's offset, rad, to its
    /// PD targets (`train.warm_start_push`; with residual actions the
    /// target is the offset / π, clamped to [-1, 1], over the value's
    /// [`EnvConfig::residual_scale`] factor and clamped again). Returns (`N *
    /// obs_dim` observations, `N * act_dim` targets).
    pub fn warm_start_data(
        &self,
        clips: &[usize],
        copies: usize,
        pushes: &[crate::sim::push::PushOffset],
        rng: &mut ChaCha8Rng,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        use crate::augment::stf::{perturb, refresh_bodies};
        let lib = self.ctx.lib;
        let needs_next = self.ctx.cfg.residual_action || self.ctx.cfg.reference_obs;
        let mut starts = Vec::new();
        for &c in clips {
            let row = &lib.clips[c];
            let allowed = crate::augment::ats::start_frames(&lib.frames[c]);
            let eps = *self.stf.eps_for(row.class as u32);
            for f in (0..allowed.len()).filter(|f| allowed[*f]) {
                let (Some(s), Some(next)) = (lib.state(c, f), lib.state(c, f + 1)) else {
                    continue;
                };
                let push = pushes
                    .iter()
                    .find(|p| p.clip == c && (p.window.start..p.window.release).contains(&f))
                    .map(|p| p.offset.as_slice());
                // With residual actions the next frame is the feed-forward
                // part, so the policy's own part is zero, or a push offset.
                let target = if self.ctx.cfg.residual_action {
                    match push {
                        // the residual that adds o: o / π over the
                        // value's gain (`residual_scale`)
                        Some(o) => {
                            let mut t = feed_forward(o);
                            let g = &self.ctx.residual_gain;
                            if !g.is_empty() {
                                t.iter_mut().zip(g).for_each(|(t, g)| {
                                    // a gain of 0 leaves the value no
                                    // residual to fit (its joint takes
                                    // the feed-forward pose alone)
                                    *t = if *g == 0.0 {
                                        0.0
                                    } else {
                                        (*t / g).clamp(-1.0, 1.0)
                                    }
                                });
                            }
                            t
                        }
                        None => vec![0.0; next.joint_rot.len()],
                    }
                } else {
                    let lead = self.ctx.cfg.feed_forward_lead;
                    let mut t = lead_target(&s.joint_rot, &next.joint_rot, lead);
                    if let Some(o) = push {
                        t.iter_mut().zip(o).for_each(|(t, o)| *t += o);
                    }
                    feed_forward(&t)
                };
                for k in 0..=copies {
                    let start = if k == 0 {
                        s.clone()
                    } else {
                        let mut o = perturb(&s, &eps, self.stf.noise, rng);
                        refresh_bodies(&s, &mut o, &self.ctx.model);
                        o
                    };
                    let traj = Trajectory {
                        target_skill: row.skill.clone(),
                        condition: row.class as u32,
                        start,
                        start_kind: StartKind::Rsi,
                        noised: k > 0,
                        fallback: false,
                        centroid: (c as u32, f as u32),
                        connect: (c as u32, f as u32),
                        beta: 1.0,
                        n_masked: 0,
                        steps: if needs_next {
                            // the start frame and the next one, which the
                            // feed-forward action and the reference
                            // observation read
                            [f, f + 1]
                                .map(|f| Step {
                                    masked: false,
                                    ref_clip: Some(c as u32),
                                    ref_frame: Some(f as u32),
                                })
                                .to_vec()
                        } else {
                            vec![Step {
                                masked: false,
                                ref_clip: None,
                                ref_frame: None,
                            }]
                        },
                        simulated: false,
                    };
                    starts.push((traj, target.clone()));
                }
            }
        }
        ensure!(
            !starts.is_empty(),
            "warm start: no frame of the training clips has a valid next frame"
        );
        let ctx = &self.ctx;
        let he = self.he.as_ref();
        let rows = starts
            .into_par_iter()
            .map(|(t, target)| {
                let key = (t.connect.0 as usize, t.connect.1 as usize);
                let ((_, ep, mut row), _) = ctx.start(t, key, he)?;
                if let Some(h) = he {
                    let emb = h.encode(&ep.hist, &mut EncoderCache::default());
                    let d = h.dim();
                    let od = row.len();
                    row[od - d..].copy_from_slice(&emb);
                }
                Ok((row, target))
            })
            .collect::<Result<Vec<_>>>()?;
        let mut obs = Vec::with_capacity(rows.len() * ctx.obs_dim);
        let mut targets = Vec::with_capacity(rows.len() * ctx.act_dim);
        for (o, t) in rows {
            obs.extend(o);
            targets.extend(t);
        }
        Ok((obs, targets))
    }

    /// Recompute the start weights from the ATS table (uniform when ATS is off).
    pub fn refresh_ats(&mut self) {
        let p = if self.ctx.cfg.ats {
            self.ctx.cfg.ats_params
        } else {
            AtsParams {
                lambda_s: 0.0,
                lambda_c: 0.0,
                lambda_i: 0.0,
                ..self.ctx.cfg.ats_params
            }
        };
        self.ats_weights = self.ats.weights(&p);
    }

    /// Set the object assist's strength for the coming steps
    /// ([`EnvConfig::object_assist`]; 0 = off).
    pub fn set_object_assist(&mut self, strength: f32) {
        self.ctx.cfg.object_assist = strength;
    }

    /// Set the floor of the ball's factors in the SM training reward for
    /// the coming steps ([`EnvConfig::object_floor`]; 0 = off).
    pub fn set_object_floor(&mut self, floor: f64) {
        self.ctx.cfg.object_floor = floor;
    }

    /// The ATS table.
    pub fn ats(&self) -> &Ats {
        &self.ats
    }

    /// The ATS records (clip, start frame, episode mean reward) of the
    /// episodes finished since the last call, in the order they were
    /// folded into the table.
    pub fn take_ats_log(&mut self) -> Vec<(usize, usize, f64)> {
        std::mem::take(&mut self.ats_log)
    }

    /// Set the ATS table to `base` with `records` folded in, in order (the
    /// records of every rank of a data-parallel run, so that all ranks hold
    /// the same table), and refresh the weights.
    pub fn replay_ats(&mut self, base: Ats, records: &[(usize, usize, f64)]) {
        self.ats = base;
        for &(c, f, r) in records {
            self.ats.record(c, f, r, self.ctx.cfg.ats_update);
        }
        self.refresh_ats();
    }

    /// Replace the ATS table (a resumed run) and refresh the weights.
    pub fn set_ats(&mut self, ats: Ats) {
        self.ats = ats;
        self.refresh_ats();
    }

    /// What the success rules see of each environment after the last step
    /// (for an environment whose episode ended, its final state).
    pub fn probes(&self) -> &[Probe] {
        &self.probes
    }

    /// The reference state environment `e`'s running episode is scored
    /// against at its current step (continued references anchored; `None`
    /// when masked or right after a reset, before the first step).
    pub fn reference_of(&self, e: usize) -> Option<State> {
        let ep = self.eps.get(e)?;
        (ep.t > 0).then(|| self.ctx.reference(ep, ep.at)).flatten()
    }

    /// The simulated state of environment `e` now: after its last step
    /// (the state the reward, the termination rules and the continuation
    /// saw), or its start after a reset. `None` for an unknown `e`.
    pub fn state_of(&self, e: usize) -> Option<State> {
        self.worlds.get(e).map(World::get_state)
    }

    /// The SM reward of each environment at the last step (`None` when masked).
    pub fn sm_rewards(&self) -> &[Option<f64>] {
        &self.sm
    }

    /// Keep each step's posture and reference ([`HumanoidEnv::take_recorded`]).
    pub fn set_recording(&mut self, on: bool) {
        self.record = on;
    }

    /// Each environment's last step when recording is on (for an
    /// environment whose episode ended, its final step), moved out.
    pub fn take_recorded(&mut self) -> Vec<Option<RecordedStep>> {
        std::mem::take(&mut self.records)
    }

    /// Take the totals since the last call.
    pub fn take_stats(&mut self) -> EnvStats {
        std::mem::take(&mut self.stats)
    }

    /// Draw a start trajectory and its ATS key.
    fn draw(&mut self, rng: &mut ChaCha8Rng) -> Result<(Trajectory, (usize, usize))> {
        if self.ctx.cfg.sim_start_prob > 0.0 {
            use rand::Rng;
            let u: f64 = rng.random();
            if u < self.ctx.cfg.sim_start_prob && !self.sim_pool.is_empty() {
                let i = rng.random_range(0..self.sim_pool.len());
                return Ok(self.sim_start(i));
            }
        }
        let mut t = self
            .sampler
            .sample(&self.ats_weights, &self.stf, rng)
            .context("no clip of the training skills has a start frame")?;
        let h = self.stf.horizon;
        let mut key = (t.connect.0 as usize, t.connect.1 as usize);
        if self.ctx.cfg.nsi_follow && t.noised {
            let (c, f) = (t.centroid.0 as usize, t.centroid.1 as usize);
            t.steps = self.sampler.follow(c, f + 1, h);
            t.connect = t.centroid;
            t.n_masked = 0;
            key = (c, f);
        } else if t.beta >= 1.0 && t.n_masked == 0 {
            t.steps = self.sampler.follow(key.0, key.1 + 1, h);
        }
        if self.ctx.cfg.object_perturb {
            perturb_objects(&mut t.start, rng);
        }
        if let Some(c) = self.ctx.cfg.condition {
            t.condition = c;
        }
        self.stats.starts.add(t.start_kind, t.noised);
        self.stats.n_masked_sum += t.n_masked as u64;
        Ok((t, key))
    }

    /// The trajectory that starts from pool state `i` and follows the rest
    /// of its clip, and its ATS key (which its episode does not update).
    fn sim_start(&mut self, i: usize) -> (Trajectory, (usize, usize)) {
        let SimStart { clip, frame, state } = self.sim_pool[i].clone();
        let c = &self.ctx.lib.clips[clip as usize];
        let steps = self
            .sampler
            .follow(clip as usize, frame as usize + 1, self.stf.horizon);
        let t = Trajectory {
            target_skill: c.skill.clone(),
            condition: self.ctx.cfg.condition.unwrap_or(c.class as u32),
            start: state,
            start_kind: StartKind::Rsi,
            noised: false,
            fallback: false,
            centroid: (clip, frame),
            connect: (clip, frame),
            beta: 1.0,
            n_masked: 0,
            steps,
            simulated: true,
        };
        self.stats.sim_starts += 1;
        (t, (clip as usize, frame as usize))
    }

    /// The pool of [`EnvConfig::sim_start_prob`] and the slot its next
    /// state replaces once full, for a checkpoint.
    pub fn sim_pool(&self) -> (&[SimStart], usize) {
        (&self.sim_pool, self.sim_next)
    }

    /// Restore the pool of a checkpoint ([`HumanoidEnv::sim_pool`]).
    ///
    /// # Errors
    /// More than [`SIM_START_POOL`] states, a slot outside the pool, or a
    /// state whose clip or frame this library does not have.
    pub fn set_sim_pool(&mut self, pool: Vec<SimStart>, next: usize) -> Result<()> {
        ensure!(
            pool.len() <= SIM_START_POOL && (next < SIM_START_POOL || pool.is_empty()),
            "checkpoint with {} simulated starts (at most {SIM_START_POOL}) and next slot {next}",
            pool.len()
        );
        for p in &pool {
            let frames = self.ctx.lib.frames.get(p.clip as usize).map(|f| f.frames);
            ensure!(
                frames.is_some_and(|n| (p.frame as usize) + 1 < n),
                "checkpoint simulated start at clip {} frame {}: not a frame of this library \
                 with one after it",
                p.clip,
                p.frame
            );
        }
        self.sim_pool = pool;
        self.sim_next = next;
        Ok(())
    }

    /// Start every draw in a fresh world, in parallel.
    fn start_all(
        &self,
        draws: Vec<(Trajectory, (usize, usize))>,
    ) -> Result<Vec<(Started, Vec<f32>)>> {
        let ctx = &self.ctx;
        let he = self.he.as_ref();
        draws
            .into_par_iter()
            .map(|(t, key)| ctx.start(t, key, he))
            .collect()
    }

    /// For each (env, feature): the embedding of its history into its
    /// observation row, then the feature pushed as the newest frame.
    fn embed_and_push(&mut self, feats: &[(usize, Vec<f32>)]) -> Result<()> {
        let Some(he) = &self.he else {
            return Ok(());
        };
        let od = self.ctx.obs_dim;
        let d = he.dim();
        let mut pushed: Vec<Option<&[f32]>> = vec![None; self.eps.len()];
        for (e, f) in feats {
            debug_assert!(
                pushed[*e].is_none(),
                "environment {e} embedded twice in one step"
            );
            pushed[*e] = Some(f);
        }
        // each environment's window moves on by one frame per step, so
        // its cache leaves only the positions next to the window's ends
        // to compute
        self.obs
            .par_chunks_mut(od)
            .zip(self.eps.par_iter_mut())
            .zip(pushed.into_par_iter())
            .for_each(|((row, ep), f)| {
                if let Some(f) = f {
                    let emb = he.encode(&ep.hist, &mut ep.he_cache);
                    row[od - d..].copy_from_slice(&emb);
                    push_history(&mut ep.hist, f);
                }
            });
        Ok(())
    }

    /// The feed-forward action of world `e`'s coming step (`[J*3]`, in
    /// [-1, 1]; empty without [`EnvConfig::residual_action`]): the next
    /// reference frame's joint rotations / π, with the push offsets of
    /// [`EnvConfig::push_feed_forward`] and the hand of
    /// [`EnvConfig::ball_hand`]; the policy's action is added to it.
    pub fn feed_forward_of(&self, e: usize) -> &[f32] {
        &self.eps[e].ff
    }

    /// The running episodes, for a checkpoint.
    pub fn snapshot(&self) -> Vec<EpisodeRecord> {
        self.eps
            .iter()
            .map(|ep| EpisodeRecord {
                traj: ep.traj.clone(),
                ats_key: ep.ats_key,
                actions: ep.actions.clone(),
                assists: ep.assists.clone(),
                floors: ep.floors.clone(),
            })
            .collect()
    }

    /// Rebuild the running episodes of a checkpoint: every world from its
    /// start, replaying its actions.
    pub fn restore(&mut self, recs: Vec<EpisodeRecord>) -> Result<()> {
        ensure!(
            recs.len() == self.worlds.len(),
            "checkpoint has {} running episodes; this run has {} environments",
            recs.len(),
            self.worlds.len()
        );
        let ad = self.ctx.act_dim;
        let od = self.ctx.obs_dim;
        for r in &recs {
            let longest = r.traj.policy_steps().max(self.ctx.cfg.continue_steps);
            ensure!(
                r.actions.len() % ad == 0 && r.actions.len() / ad <= longest,
                "checkpoint episode with {} action values does not fit its trajectory",
                r.actions.len()
            );
            ensure!(
                r.assists.len() <= r.actions.len() / ad,
                "checkpoint episode with {} assist strengths for {} steps",
                r.assists.len(),
                r.actions.len() / ad
            );
            ensure!(
                r.floors.len() <= r.actions.len() / ad,
                "checkpoint episode with {} reward floors for {} steps",
                r.floors.len(),
                r.actions.len() / ad
            );
        }
        let ctx = &self.ctx;
        let he = self.he.as_ref();
        // per env: world, episode, observation row, and the features in
        // order (start, then one per replayed step)
        let replayed = recs
            .into_par_iter()
            .map(|r| -> Result<(Started, Vec<Vec<f32>>)> {
                let ((mut w, mut ep, mut row), f0) = ctx.start(r.traj, r.ats_key, he)?;
                let mut feats = vec![f0];
                for (i, a) in r.actions.chunks_exact(ad).enumerate() {
                    let assist = r.assists.get(i).copied().unwrap_or(0.0);
                    let floor = r.floors.get(i).copied().unwrap_or(0.0);
                    let c = Control {
                        action: a,
                        assist,
                        floor,
                    };
                    let o = ctx.advance(&mut w, &mut ep, c, he, false, &mut row);
                    feats.push(o.feature);
                }
                Ok(((w, ep, row), feats))
            })
            .collect::<Result<Vec<_>>>()?;
        let mut last = Vec::with_capacity(replayed.len());
        self.worlds.clear();
        self.eps.clear();
        for (e, ((w, mut ep, row), mut feats)) in replayed.into_iter().enumerate() {
            self.obs[e * od..(e + 1) * od].copy_from_slice(&row);
            let newest = feats.pop().unwrap_or_default();
            if self.he.is_some() {
                for f in &feats {
                    push_history(&mut ep.hist, f);
                }
            }
            self.worlds.push(w);
            self.eps.push(ep);
            last.push((e, newest));
        }
        self.embed_and_push(&last)
    }

    /// Per-env outcomes of a step: masked rewards replaced, statistics
    /// recorded; returns the rewards.
    fn score(&mut self, outs: &[Outcome]) -> Vec<f32> {
        let n = outs.len();
        let clip_of = |ep: &Episode| ep.ats_key.0;
        let mut by_clip: std::collections::BTreeMap<usize, (f64, usize)> = Default::default();
        let (mut all, mut cnt) = (0.0, 0usize);
        for (ep, o) in self.eps.iter().zip(outs) {
            if let Some(r) = o.reward {
                let t = by_clip.entry(clip_of(ep)).or_default();
                t.0 += r;
                t.1 += 1;
                all += r;
                cnt += 1;
            }
        }
        let mut rewards = vec![0f32; n];
        for (e, o) in outs.iter().enumerate() {
            self.stats.steps += 1;
            rewards[e] = match o.reward {
                Some(r) => {
                    self.stats.reward_sum += r;
                    self.stats.sm_sum += o.sm.unwrap_or(0.0);
                    if let Some(t) = o.sm_terms {
                        for (acc, v) in self.stats.sm_factor_sums.iter_mut().zip(t) {
                            *acc += v;
                        }
                    }
                    r as f32
                }
                None => {
                    self.stats.masked += 1;
                    match self.ctx.cfg.masked_reward {
                        MaskedReward::Zero => 0.0,
                        MaskedReward::ClipMean => match by_clip.get(&clip_of(&self.eps[e])) {
                            Some((s, k)) => (s / *k as f64) as f32,
                            None if cnt > 0 => (all / cnt as f64) as f32,
                            None => 0.0,
                        },
                    }
                }
            };
        }
        rewards
    }
}

impl VecEnv for HumanoidEnv<'_> {
    fn num_envs(&self) -> usize {
        self.worlds.len()
    }

    fn obs_dim(&self) -> usize {
        self.ctx.obs_dim
    }

    fn act_dim(&self) -> usize {
        self.ctx.act_dim
    }

    fn observe(&self) -> Vec<f32> {
        self.obs.clone()
    }

    fn step(&mut self, actions: &[f32], rng: &mut ChaCha8Rng) -> Result<StepResult> {
        let (n, od, ad) = (self.worlds.len(), self.ctx.obs_dim, self.ctx.act_dim);
        if actions.len() != n * ad {
            bail!(
                "{} action values for {n} environments of {ad}",
                actions.len()
            );
        }
        let ctx = &self.ctx;
        let he = self.he.as_ref();
        let record = self.record;
        let (assist, floor) = (ctx.cfg.object_assist, ctx.cfg.object_floor);
        let mut outs: Vec<Outcome> = self
            .worlds
            .par_iter_mut()
            .zip(self.eps.par_iter_mut())
            .zip(self.obs.par_chunks_mut(od))
            .zip(actions.par_chunks_exact(ad))
            .map(|(((w, ep), out), action)| {
                let c = Control {
                    action,
                    assist,
                    floor,
                };
                ctx.advance(w, ep, c, he, record, out)
            })
            .collect();
        let feats: Vec<(usize, Vec<f32>)> = outs
            .iter_mut()
            .enumerate()
            .map(|(e, o)| (e, std::mem::take(&mut o.feature)))
            .collect();
        self.embed_and_push(&feats)?;
        let rewards = self.score(&outs);
        self.sm = outs.iter().map(|o| o.sm).collect();
        self.probes = outs
            .iter_mut()
            .map(|o| std::mem::take(&mut o.probe))
            .collect();
        if self.record {
            self.records = outs.iter_mut().map(|o| o.record.take()).collect();
        }
        // in environment order, so the pool does not depend on the threads
        for o in &mut outs {
            if let Some(c) = o.capture.take() {
                if self.sim_pool.len() < SIM_START_POOL {
                    self.sim_pool.push(c);
                } else {
                    self.sim_pool[self.sim_next] = c;
                    self.sim_next = (self.sim_next + 1) % SIM_START_POOL;
                }
            }
        }
        let mut res = StepResult {
            rewards,
            terminated: vec![false; n],
            truncated: vec![false; n],
            final_obs: vec![0.0; n * od],
        };
        let mut done = Vec::new();
        for (e, o) in outs.iter().enumerate() {
            let term = o.fall || o.collapse || o.lost.is_some();
            if term || o.timeout {
                res.terminated[e] = term;
                res.truncated[e] = !term;
                res.final_obs[e * od..(e + 1) * od]
                    .copy_from_slice(&self.obs[e * od..(e + 1) * od]);
                let ep = &self.eps[e];
                self.stats.episodes += 1;
                self.stats.length_sum += ep.t as u64;
                self.stats.falls += o.fall as u64;
                self.stats.collapses += (o.collapse && !o.fall) as u64;
                let lost = o.lost.filter(|_| !o.fall && !o.collapse);
                self.stats.lost += lost.is_some() as u64;
                self.stats.lost_object += (lost == Some(Lost::Object)) as u64;
                self.stats.continuations += (!ep.cont.is_empty()) as u64;
                if ep.n > 0 && !ep.traj.simulated {
                    let (c, f) = ep.ats_key;
                    let r = ep.sum / ep.n as f64;
                    self.ats.record(c, f, r, self.ctx.cfg.ats_update);
                    self.ats_log.push((c, f, r));
                }
                done.push(e);
            }
        }
        if !done.is_empty() {
            let mut draws = Vec::with_capacity(done.len());
            for _ in &done {
                draws.push(self.draw(rng)?);
            }
            let started = self.start_all(draws)?;
            let mut feats = Vec::with_capacity(done.len());
            for (&e, ((w, ep, row), f)) in done.iter().zip(started) {
                self.obs[e * od..(e + 1) * od].copy_from_slice(&row);
                self.worlds[e] = w;
                self.eps[e] = ep;
                feats.push((e, f));
            }
            self.embed_and_push(&feats)?;
        }
        Ok(res)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(root: [f32; 3], ball: [f32; 3]) -> State {
        let sk = Skeleton::MocapHumanoid;
        let mut s = State {
            root_pos: root,
            body_pos: vec![0.0; 3 * sk.n_bodies()],
            obj_pos: ball.to_vec(),
            ..State::default()
        };
        for b in s.body_pos.chunks_exact_mut(3) {
            b.copy_from_slice(&root);
        }
        s
    }

    #[test]
    fn tracking_is_lost_by_key_points_or_a_ball_the_reference_keeps_close() {
        let sk = Skeleton::MocapHumanoid;
        let r = state([0.0, 0.0, 1.0], [0.5, 0.0, 0.5]);
        // 0.4 m off everywhere: lost at 0.3, kept at 0.5 and without the rule
        let s = state([0.4, 0.0, 1.0], [0.9, 0.0, 0.5]);
        assert_eq!(
            tracking_lost(&s, Some(&r), sk, 0.3, 0.0, 0.0),
            Some(Lost::KeyPoints)
        );
        assert_eq!(tracking_lost(&s, Some(&r), sk, 0.5, 0.0, 0.0), None);
        assert_eq!(tracking_lost(&s, Some(&r), sk, 0.0, 0.0, 0.0), None);
        // masked step: no key-point test
        assert_eq!(tracking_lost(&s, None, sk, 0.3, 0.0, 0.0), None);
        // the ball 2 m from the root while the reference holds it
        let far = state([0.0, 0.0, 1.0], [2.0, 0.0, 0.5]);
        assert_eq!(
            tracking_lost(&far, Some(&r), sk, 0.0, 1.5, 0.0),
            Some(Lost::Object)
        );
        assert_eq!(tracking_lost(&far, Some(&r), sk, 0.0, 2.5, 0.0), None);
        // a shot: the reference's ball has left too
        let shot = state([0.0, 0.0, 1.0], [3.0, 0.0, 3.0]);
        assert_eq!(tracking_lost(&far, Some(&shot), sk, 0.0, 1.5, 0.0), None);
        // the ball near the root but 0.8 m below the reference's: lost by
        // the object-error rule at 0.75 m, kept at 1.0 m and without it
        let rolling = state([0.0, 0.0, 1.0], [0.5, 0.0, 0.12]);
        let high = state([0.0, 0.0, 1.0], [0.5, 0.0, 0.92]);
        assert_eq!(
            tracking_lost(&rolling, Some(&high), sk, 0.0, 1.5, 0.75),
            Some(Lost::Object)
        );
        assert_eq!(
            tracking_lost(&rolling, Some(&high), sk, 0.0, 1.5, 1.0),
            None
        );
        assert_eq!(
            tracking_lost(&rolling, Some(&high), sk, 0.0, 1.5, 0.0),
            None
        );
        // masked step: no reference, no object-error test
        assert_eq!(tracking_lost(&rolling, None, sk, 0.0, 0.0, 0.75), None);
    }

    #[test]
    fn the_reference_block_is_the_next_frame_relative_to_the_character_in_its_heading_frame() {
        let sk = Skeleton::MocapHumanoid;
        let n = reference_obs_dim(1);
        assert_eq!(n, 63);
        // the character faces +y (heading +90 degrees)
        let h = std::f32::consts::FRAC_PI_4.sin();
        let mut s = state([0.0, 0.0, 0.9], [0.5, 0.0, 0.5]);
        s.root_rot = [0.0, 0.0, h, h];
        // the reference: 1 m further along world +x, ball 0.2 m higher,
        // facing +x, moving at 2 m/s along +x
        let mut r = state([1.0, 0.0, 0.9], [1.5, 0.0, 0.7]);
        r.root_rot = [0.0, 0.0, 0.0, 1.0];
        r.root_linvel = [2.0, 0.0, 0.0];
        let mut out = vec![f32::NAN; n];
        write_reference_obs(&s, Some(&r), sk, &mut out);
        let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
        assert!(close(out[0], 0.9));
        // world +x is the character's -y (its right)
        for k in 0..18 {
            let d = &out[1 + 3 * k..4 + 3 * k];
            assert!(
                close(d[0], 0.0) && close(d[1], -1.0) && close(d[2], 0.0),
                "{d:?}"
            );
        }
        // heading difference -90 degrees
        assert!(close(out[55], 0.0) && close(out[56], -1.0));
        assert!(close(out[57], 0.0) && close(out[58], -2.0) && close(out[59], 0.0));
        assert!(close(out[60], 0.0) && close(out[61], -1.0) && close(out[62], 0.2));
        // no reference yet: zeros
        write_reference_obs(&s, None, sk, &mut out);
        assert!(out.iter().all(|v| *v == 0.0));
    }

    #[test]
    fn a_lead_extrapolates_along_the_step_and_zero_is_the_next_frame() {
        let (now, next) = ([0.1, -0.2, 0.0], [0.2, -0.1, 0.5]);
        assert_eq!(lead_target(&now, &next, 0.0), next.to_vec());
        let two = lead_target(&now, &next, 2.0);
        for (v, want) in two.iter().zip([0.4, 0.1, 1.5]) {
            assert!((v - want).abs() < 1e-6, "{two:?}");
        }
    }

    #[test]
    fn the_feed_forward_action_is_the_joint_rotation_over_pi_clipped() {
        let pi = std::f32::consts::PI;
        assert_eq!(
            feed_forward(&[0.0, pi / 2.0, -pi / 4.0, 4.0, -4.0]),
            vec![0.0, 0.5, -0.25, 1.0, -1.0]
        );
    }

    #[test]
    fn the_phase_lead_is_the_apex_gap_or_the_gap_across_the_floor() {
        // balls in free flight from the floor (centre `rest` m up) at
        // `v0` m/s, `t` s after their bounce: (z, vz)
        let (g, rest) = (GRAVITY as f32, 0.12f32);
        let ball = |v0: f32, t: f32| (rest + v0 * t - 0.5 * g * t * t, v0 - g * t);
        let close = |a: f64, b: f64| (a - b).abs() < 1e-4;
        // the same bounce: no lead; a lower bounce with the same time to
        // its apex left: none either, whatever the height gap
        assert!(close(
            ball_phase_lead(ball(4.0, 0.2), ball(4.0, 0.2), rest),
            0.0
        ));
        let (low, high) = (ball(3.0, 3.0 / g - 0.1), ball(4.5, 4.5 / g - 0.1));
        assert!((high.0 - low.0) > 0.3);
        assert!(close(ball_phase_lead(low, high, rest), 0.0));
        // 50 ms further along the same flight: 50 ms ahead; the converse
        assert!(close(
            ball_phase_lead(ball(4.0, 0.25), ball(4.0, 0.2), rest),
            0.05
        ));
        assert!(close(
            ball_phase_lead(ball(4.0, 0.2), ball(4.0, 0.25), rest),
            -0.05
        ));
        // the simulated ball 20 ms past its bounce, the reference's 30 ms
        // before its own (the flight of 0.9 s from its bounce at 4.5 m/s
        // ends 0.917 s after): 50 ms ahead, not a second behind
        let flight = 2.0 * 4.5 / g;
        let falling = ball(4.5, flight - 0.03);
        let lead = ball_phase_lead(ball(3.5, 0.02), falling, rest);
        assert!(close(lead, 0.05), "{lead}");
        // and the converse: the reference's ball has bounced, ours not yet
        let lead = ball_phase_lead(falling, ball(3.5, 0.02), rest);
        assert!(close(lead, -0.05), "{lead}");
    }
}
