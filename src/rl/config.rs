//! The settings of the `[train]` recipe table ([`TrainConfig`], with the
//! size presets and the PPO keys) and the description of a trained policy
//! ([`PolicyMeta`], `policy.meta.json`), which training writes and
//! evaluation and export read.

use crate::augment::ats::Update;
use crate::augment::seam::SeamMatch;
use crate::augment::settings::StfConfig;
use crate::reward::{ContactDetect, ContactRule, RootRot, WeightOverrides};
use crate::rl::humanoid::{JointSet, MaskedReward, Method};
use crate::rl::PpoConfig;
use anyhow::Result;
use serde::{Deserialize, Serialize};

/// Command-line switches of `skillaug train` (each, when given, overrides
/// the recipe).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Switches {
    /// `--method`.
    pub method: Option<Method>,
    /// `--nsi`.
    pub nsi: bool,
    /// `--stg`.
    pub stg: bool,
    /// `--stf`.
    pub stf: bool,
    /// `--ats`.
    pub ats: bool,
    /// `--he`.
    pub he: bool,
    /// Residual actions (`train.residual_action`; the `+Res` of a method
    /// label).
    pub residual_action: bool,
    /// The reference observation (`train.reference_obs`; `+RefObs`).
    pub reference_obs: bool,
    /// `--device`.
    pub device: Option<crate::nn::DeviceName>,
    /// `--resume`.
    pub resume: bool,
}

impl Switches {
    /// Apply the given switches to `cfg` (a switch only turns a component
    /// on; `--method` replaces the recipe's).
    pub fn apply(&self, cfg: &mut TrainConfig) {
        if let Some(m) = self.method {
            cfg.method = m;
        }
        cfg.nsi |= self.nsi;
        cfg.stg |= self.stg;
        cfg.stf |= self.stf;
        cfg.ats |= self.ats;
        cfg.he |= self.he;
        cfg.residual_action |= self.residual_action;
        cfg.reference_obs |= self.reference_obs;
    }
}

/// Size presets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// Sized for two CPU cores.
    #[default]
    Cpu,
    /// The paper's Table 6.
    Paper,
}

/// Settings of the `[train]` recipe table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// "sm" or "dm".
    pub method: Method,
    /// Skills to train (empty = every skill of the library).
    pub skills: Vec<String>,
    /// ε-NSI baseline: neighbourhood starts without the connection rule.
    pub nsi: bool,
    /// STG starts (needs `stg_edges.parquet`).
    pub stg: bool,
    /// STF starts: neighbourhood starts connected with masked states.
    pub stf: bool,
    /// Adaptive Trajectory Sampling.
    pub ats: bool,
    /// History encoder embedding in the observation.
    pub he: bool,
    /// Folder with `he.safetensors` ("" = the input folder).
    pub he_dir: String,
    /// p_e when `stg` (Table 7).
    pub p_e: f64,
    /// p_n when `nsi` or `stf` (Table 7).
    pub p_n: f64,
    /// Size preset; the keys below override it.
    pub preset: Preset,
    /// Environments (preset: 128 cpu, 2048 paper).
    pub num_envs: Option<usize>,
    /// Policy steps per environment per iteration (32).
    pub horizon: Option<usize>,
    /// Total samples to collect.
    pub samples: u64,
    /// Training episode length T, policy steps (60).
    pub episode_length: usize,
    /// Early termination on a fall.
    pub early_termination: bool,
    /// Fall threshold, m.
    pub fall_height: f32,
    /// End an episode when an unmasked SM reward is below this (0 = off).
    pub collapse_reward: f64,
    /// "clip-mean" (the reference code's rule, Ingrid789/SkillMimic-V2
    /// `skillmimic/env/tasks/skillmimic1_rand.py`) or "zero".
    pub masked_reward: MaskedReward,
    /// SM contact graph: "paper" (three pairs) or "reference".
    pub contacts: ContactRule,
    /// How the simulation detects the ball-hands contact: "proximity"
    /// (a hand within `contact_radius` of the ball, what the data's flag
    /// measures), "touch" (touching pairs at any substep) or "touch-last".
    pub contact_detect: ContactDetect,
    /// Radius of the proximity contact, m.
    pub contact_radius: f64,
    /// Root rotation term: "nearest" (exp-map branch nearest the
    /// reference's) or "raw" (reference code).
    pub root_rot: RootRot,
    /// Continue a reference that reaches its clip's end from the most
    /// similar frame of the skill (the seam), anchored to the character,
    /// so every episode lasts `episode_length` steps unless it terminates.
    pub continuation: bool,
    /// Shortest continued segment, s.
    pub seam_min_loop_s: f64,
    /// Masked steps at a seam at least (Eq. 20 alone gives N = 0 for every
    /// beta > 0.1, so the reference jumps to the seam frame at once).
    pub seam_masked_min: u32,
    /// Terminate when the mean distance of the 18 key points to the
    /// reference exceeds this, m (0 = off). 0.5 m is the failure rule of
    /// UHC and PHC (Luo et al. 2023, Section 4).
    pub term_key_distance: f64,
    /// Terminate when the ball is farther than this from the root while
    /// the reference's is not, m (0 = off); 1.5 m is the dribble success
    /// rule's bound (Ingrid789/SkillMimic-V2 `skillmimic/metric/`).
    pub term_object_distance: f64,
    /// Fall heights of single skills replacing `fall_height`, m.
    pub fall_height_by_skill: std::collections::BTreeMap<String, f32>,
    /// Warm start: epochs of behaviour cloning of the policy mean onto the
    /// next reference frame's joint rotations (zero with `residual_action`)
    /// before PPO (0 = off; see
    /// [`crate::rl::humanoid::HumanoidEnv::warm_start_data`]; on by default, docs/training.md).
    pub warm_start_epochs: usize,
    /// ε-perturbed copies of each reference state in the warm-start data.
    pub warm_start_copies: usize,
    /// Adam learning rate of the warm start.
    pub warm_start_lr: f64,
    /// Push targets for the warm start: `"off"` (the next frame's joint
    /// rotations everywhere), or `"arms"` / `"upper"`: inside every push
    /// window of the training clips the target adds the offset that
    /// `skillaug check-ball`'s push search finds on that joint group
    /// ([`crate::sim::push::push_offsets`], default search settings with
    /// `push_objective`, the run's seed), so the policy starts out pushing
    /// the ball as hard as PD targets near the clip's can. Not in the paper
    /// or the reference code. Not written when off.
    #[serde(skip_serializing_if = "is_push_off")]
    pub warm_start_push: PushJoints,
    /// First iterations that update only the critic (0 = none).
    pub critic_warmup_iters: u64,
    /// The reference code's hidden smoothness factor in the SM reward.
    pub smoothness: bool,
    /// ATS statistic update: "mean" or "halving" (reference).
    pub ats_update: Update,
    /// Iterations between checkpoints.
    pub checkpoint_every: u64,
    /// PPO settings; `hidden`, `lr`, `minibatch` come from the preset
    /// unless given here.
    pub ppo: PpoOverrides,
    /// Residual actions: PD targets = the next reference frame's joint
    /// rotations + π·a ([`crate::rl::humanoid::EnvConfig::residual_action`]);
    /// off = π·a (Eq. 11). A policy trained with it needs its reference at
    /// every step, so evaluation continues the reference past the clip end
    /// for it. Not written when off, so older settings hash alike.
    #[serde(skip_serializing_if = "is_false")]
    pub residual_action: bool,
    /// The next reference frame in the observation
    /// ([`crate::rl::humanoid::EnvConfig::reference_obs`]); evaluation
    /// continues the reference for such a policy as for `residual_action`.
    /// Not written when off.
    #[serde(skip_serializing_if = "is_false")]
    pub reference_obs: bool,
    /// Lead of the feed-forward PD targets, frames
    /// ([`crate::rl::humanoid::EnvConfig::feed_forward_lead`]; residual
    /// actions and the warm start's targets). Not written when 0.
    #[serde(skip_serializing_if = "is_zero")]
    pub feed_forward_lead: f32,
    /// With `residual_action`: the next reference frame's joint velocities
    /// as the PD drives' target velocities
    /// ([`crate::rl::humanoid::EnvConfig::velocity_feed_forward`]); off =
    /// zero target velocities (the reference code). No effect without
    /// residual actions. Not written when off.
    #[serde(skip_serializing_if = "is_false")]
    pub velocity_feed_forward: bool,
    /// Which joints get those target velocities: `"all"`, `"arms"`
    /// (shoulders, elbows, wrists and the hands) or `"fingers"` (the bodies
    /// below a wrist; the other joints keep zero
    /// target velocities; no effect without `velocity_feed_forward`)
    /// ([`crate::rl::humanoid::EnvConfig::velocity_feed_forward_joints`]).
    /// Not written when `"all"`.
    #[serde(skip_serializing_if = "is_all_joints")]
    pub velocity_feed_forward_joints: JointSet,
    /// Which joints' action noise follows `ppo.noise_correlation`: `"all"`,
    /// `"arms"` or `"fingers"` (as for `velocity_feed_forward_joints`; the
    /// other joints keep independent
    /// noise at every step; no effect without `ppo.noise_correlation`)
    /// ([`crate::rl::ppo::PpoConfig::noise_correlated_dims`]). Not written
    /// when `"all"`.
    #[serde(skip_serializing_if = "is_all_joints")]
    pub noise_correlation_joints: JointSet,
    /// With `residual_action`: factor on the policy's residual of the
    /// joints in `residual_scale_joints`, so their PD targets are
    /// π·clamp(f + scale·a, −1, 1), f the feed-forward action
    /// ([`crate::rl::humanoid::EnvConfig::residual_scale`]); 1 = f + a on
    /// every joint; 0 (not with `"all"` joints) removes those joints'
    /// residual, 0 < scale < 0.01 is refused. In training and in the
    /// evaluation of the policy. Not in the paper or the reference code.
    /// Not written when 1.
    #[serde(skip_serializing_if = "is_one_f64")]
    pub residual_scale: f64,
    /// Which joints' residual `residual_scale` scales: `"all"`, `"arms"`
    /// (shoulders, elbows, wrists and the hands, as for
    /// `velocity_feed_forward_joints`) or `"fingers"` (the bodies below a
    /// wrist). With `residual_scale = 0` those joints take the feed-forward
    /// pose alone and their action values leave the policy's Gaussian: no
    /// exploration noise and no log-likelihood term
    /// ([`crate::rl::ppo::PpoConfig::free_dims`]). Not written when
    /// `"all"`.
    #[serde(skip_serializing_if = "is_all_joints")]
    pub residual_scale_joints: JointSet,
    /// Steps over which a continued reference blends from the frame its
    /// clip ended on into the frames after the seam
    /// ([`crate::rl::humanoid::EnvConfig::seam_blend_steps`]; 0 = a jump).
    /// Not written when 0.
    #[serde(skip_serializing_if = "is_zero_usize")]
    pub seam_blend_steps: usize,
    /// Steps after a seam in which the key-point rule (`term_key_distance`)
    /// does not end an episode, so training sees the character converge
    /// onto the new frames instead of ending at the jump
    /// ([`crate::rl::humanoid::EnvConfig::term_grace_steps`]; 0 = the rule
    /// applies at every step). Not written when 0.
    #[serde(skip_serializing_if = "is_zero_usize")]
    pub term_grace_steps: usize,
    /// With continuation: a clip may be left up to this many seconds before
    /// its last valid frame, at the frame whose seam is most similar (the
    /// frames after it are dropped from training and evaluation;
    /// [`crate::augment::seam::leave_frames`]); 0 = every clip is left at
    /// its last frame. Not written when 0.
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub seam_leave_search_s: f64,
    /// Terminate when object 0 is farther than this from the reference's
    /// object 0, m (0 = off): the object's own tracking-failure rule, as
    /// `term_key_distance` is the body's
    /// ([`crate::rl::humanoid::EnvConfig::term_object_error`]). Not written
    /// when 0.
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub term_object_error: f64,
    /// Replacements of the training reward's weights, for example
    /// `{ opv = 0.5 }` or `{ oe = 0.01 }` ([`crate::reward::WeightOverrides`],
    /// `oe` for the SM reward only); empty = the
    /// paper's Table 8 (SM) or Table 9 (DM). Not written when empty.
    #[serde(default, skip_serializing_if = "WeightOverrides::is_empty")]
    pub reward_weights: WeightOverrides,
    /// Collect the next rollout while the PPO update runs, on a second
    /// thread, with a copy of the policy from before the update: the
    /// simulation overlaps the learner, and every rollout after the first
    /// is collected by the policy of one iteration earlier (a policy lag
    /// of one update, which PPO's ratio to the stored log-probabilities
    /// accounts for). Meant for `--device cuda`, where the update leaves
    /// the CPU cores free; measured in docs/training.md ("Overlapping the
    /// rollout with the update"). Off = collect, then update (the
    /// reference code). Not written when off.
    #[serde(skip_serializing_if = "is_false")]
    pub overlap_rollout: bool,
    /// Object assist at the start of training, in [0, 1] (0 = off): object
    /// 0 is pulled towards the reference's object at every step
    /// ([`crate::rl::humanoid::EnvConfig::object_assist`]), with a strength
    /// that fades linearly from this value to 0 over
    /// `object_assist_samples` ([`TrainConfig::object_assist_at`]).
    /// Evaluation never assists. Not in the paper or the reference code.
    /// Not written when 0.
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub object_assist: f64,
    /// Samples over which the object assist fades to 0 (needed when
    /// `object_assist` is on). Not written when 0.
    #[serde(skip_serializing_if = "is_zero_u64")]
    pub object_assist_samples: u64,
    /// Dead band of the object assist, m (0 = the spring always acts):
    /// while the ball is within this distance of the reference's ball the
    /// assist leaves it alone, so a weak push still costs the object terms
    /// of the reward; beyond it the ball is pulled back to the band's edge
    /// ([`crate::rl::humanoid::EnvConfig::object_assist_band`]). Not
    /// written when 0.
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub object_assist_band: f64,
    /// What a continued reference's seam frame is matched to when its clip
    /// ends: `"reference"` (the clip's last frame; one seam per clip, the
    /// STG's rule) or `"simulation"` (the simulated character and ball at
    /// that step: the skill's most similar frame then;
    /// [`crate::augment::seam::SeamMatch`]). Not in the paper or the
    /// reference code. Not written when `"reference"`.
    #[serde(skip_serializing_if = "is_reference_seam")]
    pub seam_match: SeamMatch,
    /// Factor on every joint's PD stiffness kp (kd unchanged), in training
    /// and in the evaluation of the policy
    /// ([`crate::sim::SimOptions::pd_stiffness_scale`]; 1 = the MJCF's
    /// gains, as the reference code uses them). Not in the paper or the
    /// reference code: a stronger character. Not written when 1.
    #[serde(skip_serializing_if = "is_one_f64")]
    pub pd_stiffness_scale: f64,
    /// rapier's contact recycling in training and in the evaluation of the
    /// policy ([`crate::sim::SimOptions::contact_recycling`]): a touching
    /// pair whose relative pose drifted less than 5 cm since its last full
    /// contact update keeps its contact points and normal instead of
    /// recomputing them. true = rapier's default; false recomputes
    /// every pair at every physics step, so a finger capsule (radius 5-12
    /// mm) sliding over the ball (radius 0.12 m) meets the ball where it
    /// is. Not in the paper or the reference code. Not written when true.
    #[serde(skip_serializing_if = "is_true")]
    pub contact_recycling: bool,
    /// Most frames a reference may run ahead of or behind the policy's
    /// clock between two seams when its clock follows the ball (0 = off,
    /// the clip's clock; [`crate::rl::humanoid::EnvConfig::ball_clock_frames`]),
    /// in training and in the evaluation of the policy. Not in the paper
    /// or the reference code. Not written when 0.
    #[serde(skip_serializing_if = "is_zero_usize")]
    pub ball_clock_frames: usize,
    /// Probability, in [0, 1], that a training episode starts from a state
    /// a rollout reached (at least `sim_start_after` policy steps into its
    /// episode, kept in a pool of the last 256) and follows the rest of
    /// that state's clip ([`crate::rl::humanoid::EnvConfig::sim_start_prob`]);
    /// 0 = off, every start is the STF sampler's. Evaluation never starts
    /// there. Not in the paper or the reference code. Not written when 0.
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub sim_start_prob: f64,
    /// Policy steps into an episode before its states may start others
    /// (with `sim_start_prob`). Not written when 30 (the default).
    #[serde(skip_serializing_if = "is_default_sim_start_after")]
    pub sim_start_after: usize,
    /// Density of every simulated object, kg/m^3, in place of its own, in
    /// training and in the evaluation of the policy. `None` (the default):
    /// each object's own, the ball's 1000 kg/m^3 (7.24 kg at radius
    /// 0.12 m; `skillmimic/data/assets/urdf/ball.urdf` sets no mass, so
    /// Isaac Gym's default density makes it). About 83 gives a basketball's
    /// mass, 0.6 kg (FIBA: 567-650 g). Not in the paper or the reference
    /// code. Not written when absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub object_density: Option<f64>,
    /// Weight w of an additive ball-energy bonus in the training reward
    /// (0 = off): w exp(-k (E_sim - E_ref)^2) at every step with a
    /// reference, of a class with an object, with E the ball's mechanical
    /// energy per unit mass, J/kg ([`crate::reward::energy_bonus`]). It
    /// pays for the bounce a push buys from the release on, whatever the
    /// body's factors. The reported SM reward is unchanged. Not in the
    /// paper or the reference code. Not written when 0.
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub energy_bonus: f64,
    /// Scale k of the energy bonus, (kg/J)^2. Not written when 0.02 (the
    /// default, [`crate::reward::ENERGY_BONUS_SCALE`]).
    #[serde(skip_serializing_if = "is_default_energy_bonus_scale")]
    pub energy_bonus_scale: f64,
    /// Floor ε under the product of the ball's factors in the SM training
    /// reward, in [0, 1] (0 = off, Eq. 12): at every step of a class with
    /// an object the training reward is r_b (ε + (1 - ε) r_o r_rel r_cg)
    /// ([`crate::reward::floored_total`]), so a step whose ball is lost
    /// keeps ε of the body's factor; 1 trains on r_b alone. Fades
    /// linearly to 0 over `object_floor_samples` when that is > 0
    /// ([`TrainConfig::object_floor_at`]): a curriculum from the body to
    /// the paper's reward. The SM reward that training and evaluation
    /// report is unchanged. Needs `method = "sm"`. Not in the paper or the
    /// reference code. Not written when 0.
    #[serde(skip_serializing_if = "is_zero_f64")]
    pub object_floor: f64,
    /// Samples over which `object_floor` fades to 0 (0 = it stays);
    /// refused without `object_floor`. Each iteration's floor is set from
    /// the samples learnt before it, so with `overlap_rollout` the rollout
    /// collected during an update is one iteration behind, as the object
    /// assist's is. Not written when 0.
    #[serde(skip_serializing_if = "is_zero_u64")]
    pub object_floor_samples: u64,
    /// Push offsets as feed-forward: `"off"`, or `"arms"` / `"upper"`:
    /// with `residual_action`, inside every push window of the training
    /// clips the feed-forward PD targets add the offset that `skillaug
    /// check-ball`'s push search finds on that joint group
    /// ([`crate::sim::push::push_offsets`], default search settings with
    /// `push_objective`, the run's seed;
    /// [`crate::rl::humanoid::EnvConfig::push_feed_forward`]),
    /// so the hand pushes harder than the clip's own targets make it
    /// without the policy having to find the push. In training and in the
    /// policy's evaluation (the offsets are written to `policy.meta.json`).
    /// Refused beside `warm_start_push` (which would fit the offset a
    /// second time) and without `residual_action`. With
    /// `feed_forward_lead` the offset is added to the extrapolated target.
    /// Not in the paper or the reference code. Not written when off.
    #[serde(skip_serializing_if = "is_push_off")]
    pub push_feed_forward: PushJoints,
    /// What the push search of `push_feed_forward` and `warm_start_push`
    /// optimises ([`crate::sim::push::PushObjective`]): `"ball"` (the
    /// ball's velocity and position at the release against the clip's),
    /// or `"catch"` (the ball's velocity and its position relative to the
    /// root where the clip's hand next meets it, after its bounce). Refused
    /// when neither of the two is on, and for `"sm"` (`skillaug
    /// check-ball`'s SM objective scores with the paper's weights and
    /// default reward options, not training's). Not in the paper or the
    /// reference code. Not written when `"ball"`.
    #[serde(skip_serializing_if = "is_ball_objective")]
    pub push_objective: crate::sim::push::PushObjective,
    /// Rotational inertia of the ball in training and in the policy's
    /// evaluation: `"solid"` (2/5 m r^2, the reference's URDF sphere) or
    /// `"shell"` (2/3 m r^2 with the same mass, a basketball's), which
    /// keeps less of its horizontal speed through a bounce
    /// ([`crate::sim::objects::BallInertia`]). Not in the paper or the
    /// reference code. Not written when solid.
    #[serde(skip_serializing_if = "is_solid")]
    pub ball_inertia: crate::sim::objects::BallInertia,
    /// Angular velocity damping of every simulated object, 1/s, in place
    /// of its own, in training and in the evaluation of the policy
    /// ([`crate::sim::objects::set_angular_damping`]). `None` (the
    /// default): each object's own, 0.01 (the reference's ball,
    /// `humanoid_object_task.py`). A large value (about 10) takes the spin
    /// a bounce gives the ball away before its next bounce, so a ball that
    /// left the floor rolling does not land rolling and keep all of its
    /// horizontal speed (docs/training.md, "A ball whose spin dies away").
    /// Not in the paper or the reference code. Not written when absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub object_angular_damping: Option<f64>,
    /// The ball the training reference follows between each push's release
    /// and the frame where the clip's hand meets it again: `"captured"`
    /// (the clip's) or `"simulated"`, the flight a simulated ball released
    /// without spin takes to reach the clip's ball at that frame
    /// ([`crate::sim::ball_path`]), in training and in the evaluation of
    /// the policy. Not in the paper or the reference code. Not written
    /// when captured.
    #[serde(skip_serializing_if = "is_captured")]
    pub reference_ball: crate::sim::ball_path::ReferenceBall,
    /// The hand the training reference follows while it pushes the ball:
    /// `"captured"` (the clip's) or `"on-ball"`, the pushing hand put on
    /// top of its ball and kept there while the ball speeds up, by
    /// inverse kinematics of the arm and chest ([`crate::sim::hand_path`]),
    /// in training and in the evaluation of the policy. Not in the paper
    /// or the reference code. Not written when captured.
    #[serde(skip_serializing_if = "is_captured_hand")]
    pub reference_hand: crate::sim::hand_path::ReferenceHand,
    /// Whether the pushing hand of every push window follows the simulated
    /// ball in the feed-forward PD targets of `residual_action`: the arm
    /// and chest joints solved online, at every step of a window and its
    /// blends, so that the hand sits above the ball the simulation has,
    /// led by the reference ball's motion over the drives' time constant
    /// ([`crate::rl::humanoid::EnvConfig::ball_hand`],
    /// [`crate::sim::hand_path::reach`]); the reference the reward scores
    /// is unchanged. In training and in the evaluation of the policy. Not
    /// in the paper or the reference code. Not written when off.
    #[serde(skip_serializing_if = "is_false")]
    pub hand_follows_ball: bool,
    /// Where in each push window `hand_follows_ball` starts to follow the
    /// ball: `"push"` (the window's first frame, the ball descending under
    /// the hand) or `"catch"` (the first frame of the clip's ride before
    /// the push, where its hand meets the rising ball;
    /// [`crate::sim::hand_path::FollowFrom`]). Needs `hand_follows_ball`.
    /// Not written when `"push"`.
    #[serde(skip_serializing_if = "is_follow_push")]
    pub hand_follows_ball_from: crate::sim::hand_path::FollowFrom,
    /// How far the online hand of `hand_follows_ball` moves from where the
    /// reference's pose puts it, m, at most; a ball farther off is
    /// followed only this far ([`crate::sim::hand_path::BallHand::reach`];
    /// default [`crate::sim::hand_path::REACH_MAX_SHIFT`], 0.3 m). Needs
    /// `hand_follows_ball` when not the default. Not written when the
    /// default.
    #[serde(skip_serializing_if = "is_default_reach")]
    pub hand_follows_ball_reach: f64,
}

fn is_default_reach(r: &f64) -> bool {
    *r == crate::sim::hand_path::REACH_MAX_SHIFT
}

fn is_follow_push(f: &crate::sim::hand_path::FollowFrom) -> bool {
    *f == crate::sim::hand_path::FollowFrom::Push
}

fn is_captured(b: &crate::sim::ball_path::ReferenceBall) -> bool {
    *b == crate::sim::ball_path::ReferenceBall::Captured
}

fn is_captured_hand(h: &crate::sim::hand_path::ReferenceHand) -> bool {
    *h == crate::sim::hand_path::ReferenceHand::Captured
}

fn is_ball_objective(o: &crate::sim::push::PushObjective) -> bool {
    *o == crate::sim::push::PushObjective::Ball
}

fn is_solid(b: &crate::sim::objects::BallInertia) -> bool {
    *b == crate::sim::objects::BallInertia::Solid
}

/// `start` faded linearly to 0 over `over` > 0 samples, after `samples`:
/// start (1 - samples / over), at least 0 (the schedule of
/// [`TrainConfig::object_assist_at`] and [`TrainConfig::object_floor_at`]).
fn faded(start: f64, samples: u64, over: u64) -> f64 {
    let left = 1.0 - samples as f64 / over as f64;
    start * left.max(0.0)
}

fn is_default_energy_bonus_scale(x: &f64) -> bool {
    *x == crate::reward::ENERGY_BONUS_SCALE
}

fn is_default_sim_start_after(x: &usize) -> bool {
    *x == crate::rl::humanoid::SIM_START_AFTER
}

fn is_one_f64(x: &f64) -> bool {
    *x == 1.0
}

fn is_zero_u64(x: &u64) -> bool {
    *x == 0
}

fn is_zero_f64(x: &f64) -> bool {
    *x == 0.0
}

/// Serde's `skip_serializing_if` for a count that is 0.
pub(crate) fn is_zero_usize(x: &usize) -> bool {
    *x == 0
}

fn is_zero(x: &f32) -> bool {
    *x == 0.0
}

/// The joints whose searched push offsets the warm start fits
/// (`train.warm_start_push`) or the feed-forward adds
/// (`train.push_feed_forward`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PushJoints {
    /// No offsets: the next reference frame everywhere.
    #[default]
    Off,
    /// Offsets on the shoulders, elbows and wrists
    /// ([`crate::sim::push::push_joints`]).
    Arms,
    /// Offsets on the arms, torso, spine, chest, thorax and neck.
    Upper,
}

fn is_reference_seam(m: &SeamMatch) -> bool {
    *m == SeamMatch::Reference
}

impl PushJoints {
    /// The recipe value (`"off"`, `"arms"`, `"upper"`).
    pub fn name(self) -> &'static str {
        match self {
            PushJoints::Off => "off",
            PushJoints::Arms => "arms",
            PushJoints::Upper => "upper",
        }
    }
}

fn is_push_off(p: &PushJoints) -> bool {
    *p == PushJoints::Off
}

fn is_all_joints(j: &JointSet) -> bool {
    *j == JointSet::All
}

fn is_false(b: &bool) -> bool {
    !*b
}

fn is_true(b: &bool) -> bool {
    *b
}

/// PPO keys of `[train.ppo]`; unset keys take the preset's value or the
/// SkillMimic default.
#[derive(Clone, Debug, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PpoOverrides {
    /// Hidden sizes of both networks.
    pub hidden: Option<Vec<usize>>,
    /// Adam learning rate.
    pub lr: Option<f64>,
    /// Minibatch size.
    pub minibatch: Option<usize>,
    /// Mini-epochs.
    pub epochs: Option<usize>,
    /// Action noise (std unless `sigma_is_variance`).
    pub sigma: Option<f64>,
    /// Read `sigma` as a variance (the paper's wording).
    pub sigma_is_variance: Option<bool>,
    /// Discount.
    pub gamma: Option<f64>,
    /// GAE λ.
    pub lambda: Option<f64>,
    /// Ratio clip.
    pub clip: Option<f64>,
    /// Value-loss weight.
    pub critic_coef: Option<f64>,
    /// Bounds-loss weight.
    pub bounds_coef: Option<f64>,
    /// Merge observation statistics after the update (see
    /// [`PpoConfig::norm_after_update`]).
    pub norm_after_update: Option<bool>,
    /// Standardised value targets ([`PpoConfig::normalize_value`]).
    pub normalize_value: Option<bool>,
    /// Adaptive learning rate around this KL ([`PpoConfig::kl_threshold`]).
    pub kl_threshold: Option<f64>,
    /// Policy head weights drawn from U(-b, b) ([`PpoConfig::policy_out_bound`];
    /// default 0.01); 0 = PyTorch's default `Linear` initialisation, as
    /// SkillMimic's released code. Not written when unset.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub policy_out_bound: Option<f64>,
    /// Correlation of the action noise between consecutive steps, in
    /// [0, 1) ([`PpoConfig::noise_correlation`]; 0 = independent, the
    /// default). Not written when unset.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub noise_correlation: Option<f64>,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            method: Method::Sm,
            skills: Vec::new(),
            nsi: false,
            stg: false,
            stf: false,
            ats: false,
            he: false,
            he_dir: String::new(),
            p_e: 0.1,
            p_n: 0.1,
            preset: Preset::Cpu,
            num_envs: None,
            horizon: None,
            samples: 2_000_000,
            episode_length: 60,
            early_termination: true,
            fall_height: 0.3,
            collapse_reward: 0.0,
            masked_reward: MaskedReward::ClipMean,
            contacts: ContactRule::Paper,
            contact_detect: ContactDetect::Proximity,
            contact_radius: 0.2,
            root_rot: RootRot::Nearest,
            continuation: true,
            seam_min_loop_s: 0.5,
            seam_masked_min: 0,
            term_key_distance: 0.5,
            term_object_distance: 1.5,
            fall_height_by_skill: Default::default(),
            warm_start_epochs: 50,
            warm_start_copies: 4,
            warm_start_lr: 1e-3,
            warm_start_push: PushJoints::Off,
            critic_warmup_iters: 5,
            smoothness: false,
            ats_update: Update::Mean,
            checkpoint_every: 10,
            ppo: PpoOverrides::default(),
            residual_action: false,
            reference_obs: false,
            feed_forward_lead: 0.0,
            velocity_feed_forward: false,
            velocity_feed_forward_joints: JointSet::All,
            noise_correlation_joints: JointSet::All,
            residual_scale: 1.0,
            residual_scale_joints: JointSet::All,
            seam_blend_steps: 0,
            term_grace_steps: 0,
            seam_leave_search_s: 0.0,
            term_object_error: 0.0,
            reward_weights: WeightOverrides::default(),
            overlap_rollout: false,
            object_assist: 0.0,
            object_assist_samples: 0,
            object_assist_band: 0.0,
            seam_match: SeamMatch::Reference,
            pd_stiffness_scale: 1.0,
            contact_recycling: true,
            ball_clock_frames: 0,
            sim_start_prob: 0.0,
            sim_start_after: crate::rl::humanoid::SIM_START_AFTER,
            object_density: None,
            energy_bonus: 0.0,
            energy_bonus_scale: crate::reward::ENERGY_BONUS_SCALE,
            object_floor: 0.0,
            object_floor_samples: 0,
            push_feed_forward: PushJoints::Off,
            push_objective: crate::sim::push::PushObjective::Ball,
            ball_inertia: crate::sim::objects::BallInertia::Solid,
            object_angular_damping: None,
            reference_ball: crate::sim::ball_path::ReferenceBall::Captured,
            reference_hand: crate::sim::hand_path::ReferenceHand::Captured,
            hand_follows_ball: false,
            hand_follows_ball_from: crate::sim::hand_path::FollowFrom::Push,
            hand_follows_ball_reach: crate::sim::hand_path::REACH_MAX_SHIFT,
        }
    }
}

impl TrainConfig {
    /// Environments per iteration.
    pub fn envs(&self) -> usize {
        self.num_envs.unwrap_or(match self.preset {
            Preset::Cpu => 128,
            Preset::Paper => 2048,
        })
    }

    /// Steps per environment per iteration.
    pub fn steps(&self) -> usize {
        self.horizon.unwrap_or(32)
    }

    /// Strength of the object assist for a rollout collected after
    /// `samples` samples: `object_assist` (1 - samples /
    /// `object_assist_samples`), at least 0; 0 when the assist is off.
    pub fn object_assist_at(&self, samples: u64) -> f64 {
        if self.object_assist <= 0.0 || self.object_assist_samples == 0 {
            return 0.0;
        }
        faded(self.object_assist, samples, self.object_assist_samples)
    }

    /// Floor of the ball's factors for a rollout collected after `samples`
    /// samples: `object_floor`, times (1 - samples / `object_floor_samples`)
    /// (at least 0) when that is > 0.
    pub fn object_floor_at(&self, samples: u64) -> f64 {
        if self.object_floor_samples == 0 {
            return self.object_floor;
        }
        faded(self.object_floor, samples, self.object_floor_samples)
    }

    /// The PPO configuration: preset, then overrides.
    pub fn ppo_config(&self) -> PpoConfig {
        let mut c = PpoConfig::default();
        if self.preset == Preset::Cpu {
            c.hidden = vec![256, 256];
            c.lr = 1e-4;
            c.minibatch = 2048;
        }
        let o = &self.ppo;
        macro_rules! set {
            ($($f:ident),*) => {$(if let Some(v) = &o.$f { c.$f = v.clone(); })*};
        }
        set!(
            hidden,
            lr,
            minibatch,
            epochs,
            sigma,
            sigma_is_variance,
            gamma,
            lambda,
            clip,
            critic_coef,
            bounds_coef,
            norm_after_update,
            normalize_value
        );
        if let Some(r) = o.noise_correlation {
            c.noise_correlation = r;
        }
        if o.kl_threshold.is_some() {
            c.kl_threshold = o.kl_threshold;
        }
        if let Some(b) = o.policy_out_bound {
            c.policy_out_bound = (b > 0.0).then_some(b);
        }
        c
    }
}

impl crate::config::Validate for TrainConfig {
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.range("p_e", self.p_e, 0.0, 1.0)?;
        c.range("p_n", self.p_n, 0.0, 1.0)?;
        c.range("feed_forward_lead", self.feed_forward_lead as f64, 0.0, 5.0)?;
        c.count("seam_blend_steps", self.seam_blend_steps as u64, 0, 1000)?;
        c.count("term_grace_steps", self.term_grace_steps as u64, 0, 100_000)?;
        c.range("seam_leave_search_s", self.seam_leave_search_s, 0.0, 60.0)?;
        c.range("object_assist", self.object_assist, 0.0, 1.0)?;
        c.range("object_assist_band", self.object_assist_band, 0.0, 10.0)?;
        c.range("pd_stiffness_scale", self.pd_stiffness_scale, 0.1, 100.0)?;
        c.count(
            "ball_clock_frames",
            self.ball_clock_frames as u64,
            0,
            10_000,
        )?;
        c.range("sim_start_prob", self.sim_start_prob, 0.0, 1.0)?;
        c.count("sim_start_after", self.sim_start_after as u64, 1, 100_000)?;
        c.range("energy_bonus", self.energy_bonus, 0.0, 100.0)?;
        c.range("energy_bonus_scale", self.energy_bonus_scale, 1e-6, 100.0)?;
        c.range("object_floor", self.object_floor, 0.0, 1.0)?;
        if let Some(d) = self.object_density {
            c.range("object_density", d, 1.0, 1e5)?;
        }
        if let Some(d) = self.object_angular_damping {
            c.range("object_angular_damping", d, 0.0, 1000.0)?;
        }
        if self.push_feed_forward != PushJoints::Off && self.warm_start_push != PushJoints::Off {
            anyhow::bail!(
                "{stage}.push_feed_forward already adds the searched offsets to the feed-forward \
                 targets, which the warm start then fits as a zero residual; \
                 {stage}.warm_start_push would add them a second time: set one of the two to \"off\""
            );
        }
        if self.push_objective == crate::sim::push::PushObjective::Sm {
            anyhow::bail!(
                "{stage}.push_objective = \"sm\" is check-ball's objective: its SM reward uses the \
                 paper's weights and default reward options, not this run's; use \"ball\" or \"catch\""
            );
        }
        if self.push_objective != crate::sim::push::PushObjective::Ball
            && self.push_feed_forward == PushJoints::Off
            && self.warm_start_push == PushJoints::Off
        {
            anyhow::bail!(
                "{stage}.push_objective = \"{}\" chooses what the push search of \
                 {stage}.push_feed_forward or {stage}.warm_start_push optimises, and both are \
                 \"off\": turn one on, or leave push_objective at \"ball\"",
                self.push_objective.name()
            );
        }
        c.range("residual_scale", self.residual_scale, 0.0, 1.0)?;
        if self.residual_scale > 0.0 && self.residual_scale < 0.01 {
            anyhow::bail!(
                "{stage}.residual_scale = {} must be 0 (no residual on its joints) or in \
                 [0.01, 1]",
                self.residual_scale
            );
        }
        if self.residual_scale == 0.0 && self.residual_scale_joints == JointSet::All {
            anyhow::bail!(
                "{stage}.residual_scale = 0 on every joint leaves the policy no action: set \
                 {stage}.residual_scale_joints to \"arms\" or \"fingers\", or a scale above 0"
            );
        }
        if self.residual_scale != 1.0 && !self.residual_action {
            anyhow::bail!(
                "{stage}.residual_scale = {} scales the policy's residual of \
                 {stage}.residual_action, which is off: set {stage}.residual_action = true, or \
                 leave residual_scale at 1",
                self.residual_scale
            );
        }
        if self.residual_scale_joints != JointSet::All && self.residual_scale == 1.0 {
            anyhow::bail!(
                "{stage}.residual_scale_joints = \"{}\" says which joints {stage}.residual_scale \
                 scales, and that is 1: set residual_scale below 1, or leave \
                 residual_scale_joints at \"all\"",
                self.residual_scale_joints.name()
            );
        }
        if self.hand_follows_ball && !self.residual_action {
            anyhow::bail!(
                "{stage}.hand_follows_ball moves the feed-forward targets of \
                 {stage}.residual_action: set {stage}.residual_action = true, or hand_follows_ball = false"
            );
        }
        if self.hand_follows_ball_from != crate::sim::hand_path::FollowFrom::Push
            && !self.hand_follows_ball
        {
            anyhow::bail!(
                "{stage}.hand_follows_ball_from = \"{}\" says where the hand of \
                 {stage}.hand_follows_ball starts to follow the ball, and that setting is off: \
                 set {stage}.hand_follows_ball = true, or leave hand_follows_ball_from at \"push\"",
                self.hand_follows_ball_from.name()
            );
        }
        c.range(
            "hand_follows_ball_reach",
            self.hand_follows_ball_reach,
            0.01,
            2.0,
        )?;
        if !is_default_reach(&self.hand_follows_ball_reach) && !self.hand_follows_ball {
            anyhow::bail!(
                "{stage}.hand_follows_ball_reach = {} says how far the hand of \
                 {stage}.hand_follows_ball may reach, and that setting is off: set \
                 {stage}.hand_follows_ball = true, or leave hand_follows_ball_reach at {}",
                self.hand_follows_ball_reach,
                crate::sim::hand_path::REACH_MAX_SHIFT
            );
        }
        if self.push_feed_forward != PushJoints::Off && !self.residual_action {
            anyhow::bail!(
                "{stage}.push_feed_forward adds its offsets to the feed-forward targets of \
                 {stage}.residual_action: set {stage}.residual_action = true, or push_feed_forward = \"off\""
            );
        }
        if self.object_floor > 0.0 && self.method != Method::Sm {
            anyhow::bail!(
                "{stage}.object_floor = {} floors the ball's factors of the SM reward's product, \
                 and {stage}.method is not \"sm\": set method = \"sm\", or object_floor = 0",
                self.object_floor
            );
        }
        if self.object_floor_samples > 0 && self.object_floor == 0.0 {
            anyhow::bail!(
                "{stage}.object_floor_samples = {} says over how many samples {stage}.object_floor \
                 fades, and that floor is 0: set object_floor > 0, or object_floor_samples = 0",
                self.object_floor_samples
            );
        }
        if self.object_assist > 0.0 && self.object_assist_samples == 0 {
            anyhow::bail!(
                "{stage}.object_assist = {} needs {stage}.object_assist_samples > 0 (the samples over which it fades)",
                self.object_assist
            );
        }
        c.count("num_envs", self.envs() as u64, 1, 1 << 20)?;
        c.count("horizon", self.steps() as u64, 1, 1 << 20)?;
        c.count("samples", self.samples, 1, u64::MAX)?;
        c.count("episode_length", self.episode_length as u64, 1, 1 << 24)?;
        c.finite("fall_height", self.fall_height as f64)?;
        c.finite("collapse_reward", self.collapse_reward)?;
        c.positive("contact_radius", self.contact_radius)?;
        c.non_negative("seam_min_loop_s", self.seam_min_loop_s)?;
        c.count("seam_masked_min", self.seam_masked_min as u64, 0, 10_000)?;
        c.non_negative("term_key_distance", self.term_key_distance)?;
        if let Some(b) = self.ppo.policy_out_bound {
            c.non_negative("ppo.policy_out_bound", b)?;
        }
        c.non_negative("term_object_distance", self.term_object_distance)?;
        c.non_negative("term_object_error", self.term_object_error)?;
        self.reward_weights.check(stage)?;
        for (skill, h) in &self.fall_height_by_skill {
            c.finite(&format!("fall_height_by_skill.{skill}"), *h as f64)?;
        }
        c.count(
            "warm_start_epochs",
            self.warm_start_epochs as u64,
            0,
            1 << 20,
        )?;
        c.count("warm_start_copies", self.warm_start_copies as u64, 0, 1000)?;
        c.positive("warm_start_lr", self.warm_start_lr)?;
        c.count("checkpoint_every", self.checkpoint_every, 1, u64::MAX)?;
        let o = &self.ppo;
        let p = crate::config::Check::new("train.ppo");
        if let Some(h) = &o.hidden {
            p.holds(!h.is_empty() && h.iter().all(|&n| n > 0), || {
                format!("hidden = {h:?}: needs at least one layer, every size > 0")
            })?;
        }
        for (k, v) in [
            ("lr", o.lr),
            ("sigma", o.sigma),
            ("clip", o.clip),
            ("kl_threshold", o.kl_threshold),
        ] {
            if let Some(v) = v {
                p.positive(k, v)?;
            }
        }
        for (k, v) in [
            ("critic_coef", o.critic_coef),
            ("bounds_coef", o.bounds_coef),
        ] {
            if let Some(v) = v {
                p.non_negative(k, v)?;
            }
        }
        for (k, v) in [("gamma", o.gamma), ("lambda", o.lambda)] {
            if let Some(v) = v {
                p.range(k, v, 0.0, 1.0)?;
            }
        }
        if let Some(r) = o.noise_correlation {
            p.holds((0.0..1.0).contains(&r), || {
                format!("noise_correlation = {r}: must be in [0, 1)")
            })?;
        }
        if let Some(n) = o.minibatch {
            p.count("minibatch", n as u64, 1, 1 << 30)?;
        }
        if let Some(n) = o.epochs {
            p.count("epochs", n as u64, 1, 1000)?;
        }
        Ok(())
    }
}

/// What a trained policy was trained on (`policy.meta.json`), so that
/// evaluation can refuse a library, skill set or encoder that does not match.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PolicyMeta {
    /// Layout version.
    pub format: u32,
    /// Dataset of the clips.
    pub dataset: String,
    /// Skeleton.
    pub skeleton: String,
    /// Trained skills, in clip order.
    pub skills: Vec<String>,
    /// Trained clip names.
    pub clips: Vec<String>,
    /// Objects of the worlds.
    pub objects: Vec<String>,
    /// Observation size.
    pub obs_dim: usize,
    /// Action size.
    pub act_dim: usize,
    /// Folder of the history encoder (None: trained without).
    pub he_dir: Option<String>,
    /// The training settings.
    pub train: TrainConfig,
    /// The STF settings (ε of the neighbourhood evaluation).
    pub stf: StfConfig,
    /// Iterations trained.
    pub iterations: u64,
    /// Samples trained.
    pub samples: u64,
    /// MPI ranks it was trained on (1: one process; older descriptions
    /// without the field were one process).
    #[serde(default = "one_rank", skip_serializing_if = "is_one")]
    pub ranks: usize,
    /// The push offsets of `train.push_feed_forward`, which evaluation
    /// adds as training did (empty when off; not written then).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub push_feed_forward: Vec<PushOffsetMeta>,
    /// The ball flights of `train.reference_ball = "simulated"` as training
    /// solved them; evaluation solves them again and refuses a policy
    /// whose flights now come out otherwise (empty when captured; not
    /// written then).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub reference_flights: Vec<FlightMeta>,
}

/// One simulated reference flight as `policy.meta.json` holds it
/// ([`crate::sim::ball_path::Flight`] with the clip by name).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FlightMeta {
    /// Clip name.
    pub clip: String,
    /// Release frame (the flight's first).
    pub release: usize,
    /// Catch frame.
    pub catch: usize,
    /// The solved release velocity, m/s.
    pub v_sim: [f64; 3],
    /// Whether the flight replaced the clip's ball.
    pub applied: bool,
}

/// One push window's feed-forward offset as `policy.meta.json` holds it
/// ([`crate::rl::humanoid::PushFeedForward`] with the clip by name).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PushOffsetMeta {
    /// Clip name.
    pub clip: String,
    /// First frame of the window.
    pub start: usize,
    /// The frame after the window's last (the release).
    pub release: usize,
    /// Offset of every joint, rad, `[J*3]` exp-map components.
    pub offset: Vec<f32>,
}

fn one_rank() -> usize {
    1
}

fn is_one(n: &usize) -> bool {
    *n == 1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_policy_head_bound_is_a_recipe_key_and_zero_means_the_pytorch_default() {
        let mut cfg = TrainConfig::default();
        assert_eq!(cfg.ppo_config().policy_out_bound, Some(0.01));
        cfg.ppo.policy_out_bound = Some(0.0);
        assert_eq!(cfg.ppo_config().policy_out_bound, None);
        cfg.ppo.policy_out_bound = Some(0.1);
        assert_eq!(cfg.ppo_config().policy_out_bound, Some(0.1));
        use crate::config::Validate;
        assert!(cfg.validate("train").is_ok());
        cfg.ppo.policy_out_bound = Some(-1.0);
        let e = cfg.validate("train").unwrap_err().to_string();
        assert!(e.contains("train.ppo.policy_out_bound"), "{e}");
        // unset, it is not written: older settings hash alike
        let text = toml::to_string(&TrainConfig::default()).unwrap();
        assert!(!text.contains("policy_out_bound"), "{text}");
    }
}
