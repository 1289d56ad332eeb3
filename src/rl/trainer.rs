//! The trainer of `skillaug train`: the environment set-up ([`Setup`],
//! [`environment`]), the PPO loop over the rapier3d humanoid ([`Trainer`]),
//! its checkpoint (exact resume) and the policy's metadata
//! ([`Trainer::policy_meta`]). The stage (`src/stage/train.rs`) resolves the
//! settings, loads the history encoder, drives the loop and writes the
//! outputs.
//!
//! Data-parallel runs: with a [`Comm`] of R ranks, each rank simulates
//! `envs / R` environments with its own random stream (rank r: ChaCha8
//! stream r of the seed; rank 0 is the one-process run's generator), and
//! [`Agent::update_with`] combines the ranks' batches so that every rank
//! holds the same weights, which [`Trainer::iterate`] checks after every
//! update. The iteration's metrics and the ATS table are combined over the
//! ranks too; only rank 0 should write outputs. A checkpoint holds every
//! rank's generator, episode tracker and running episodes, and resumes with
//! the same number of ranks only.

use super::comm::{fingerprint, Comm};
use super::config::{PolicyMeta, PushJoints, PushOffsetMeta, TrainConfig};
use super::humanoid::{
    EnvConfig, EnvParts, EnvStats, EpisodeRecord, HeRuntime, HumanoidEnv, JointSet,
    PushFeedForward, SimStart,
};
use super::{collect, Agent, EpisodeTracker, StepResult, VecEnv};
use crate::augment::ats::{Ats, AtsParams};
use crate::augment::seam::{SeamMatch, SeamPool};
use crate::augment::settings::StfConfig;
use crate::augment::stf::{StfParams, StfSampler};
use crate::motion::MotionLib;
use crate::reward::{DatasetKind, RewardOptions, Weights};
use crate::sim::mjcf::Model;
use crate::sim::push::{PushObjective, PushOffset};
use crate::sim::{objects, SimOptions};
use crate::table::io::StagedDir;
use crate::table::train::{MetricRow, Metrics};
use anyhow::{bail, ensure, Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Everything the environment is built from, loaded once.
pub struct Setup {
    /// The motion library.
    pub lib: MotionLib,
    /// STG edges (empty without `stg`).
    pub edges: Vec<crate::augment::stg::Edge>,
    /// The humanoid model.
    pub model: Model,
    /// Objects of the trained clips.
    pub objects: Vec<crate::sim::ObjectSpec>,
    /// Physics settings.
    pub sim: SimOptions,
    /// STF parameters with the switches applied.
    pub stf: StfParams,
    /// ATS exponents.
    pub ats_params: AtsParams,
    /// Clip ids being trained.
    pub clips: Vec<usize>,
    /// Whether perturbed starts need forward kinematics.
    pub fk: bool,
    /// Seam of every clip ([`crate::augment::seam`]).
    pub seams: Vec<Option<crate::augment::seam::Seam>>,
    /// The frames a seam may continue at with `train.seam_match =
    /// "simulation"` (empty otherwise).
    pub seam_pool: crate::augment::seam::SeamPool,
    /// The ball flights `train.reference_ball = "simulated"` solved, one
    /// per flight of the trained clips
    /// ([`crate::sim::ball_path::flight_frames`]), applied or not (empty
    /// when captured).
    pub flights: Vec<crate::sim::ball_path::Flight>,
    /// The push windows whose hand `train.reference_hand = "on-ball"` put
    /// on top of the ball, in clip and frame order (empty when captured).
    pub hands: Vec<crate::sim::hand_path::HandRepair>,
    /// The push windows whose hand `train.hand_follows_ball` moves onto
    /// the simulated ball online, in clip and frame order (empty when
    /// off; [`ball_hands`]).
    pub ball_hands: Vec<crate::sim::hand_path::BallHand>,
}

impl Setup {
    /// Load the clips of the run folder `input` and everything else the
    /// environment needs. `data_root` is `--data-root` (the humanoid models
    /// and objects; [`crate::dataset::data_root`] when `None`).
    ///
    /// # Errors
    /// As [`crate::table::load_library`] and [`Setup::from_library`].
    pub fn load(
        input: &Path,
        data_root: Option<&Path>,
        cfg: &TrainConfig,
        stf_cfg: &StfConfig,
    ) -> Result<Setup> {
        Setup::from_library(
            crate::table::load_library(input)?,
            input,
            data_root,
            cfg,
            stf_cfg,
        )
    }

    /// [`Setup::load`] on a library already loaded from `input` (evaluation
    /// checks the library against the policy first and uses the policy's
    /// STF settings).
    ///
    /// # Errors
    /// An unknown skill in `train.skills`, `--stg` on ParaHome, STG edges
    /// that are missing or of other clips, clips that need different
    /// worlds, or a model or object that cannot be read.
    pub fn from_library(
        lib: MotionLib,
        input: &Path,
        data_root: Option<&Path>,
        cfg: &TrainConfig,
        stf_cfg: &StfConfig,
    ) -> Result<Setup> {
        let (base, ats_params) = stf_cfg.params()?;
        let all = lib.skills();
        for s in &cfg.skills {
            if !all.contains(s) {
                bail!(
                    "train.skills: no skill `{s}` in {} (skills: {})",
                    input.display(),
                    all.join(", ")
                );
            }
        }
        let clips: Vec<usize> = (0..lib.clips.len())
            .filter(|c| cfg.skills.is_empty() || cfg.skills.contains(&lib.clips[*c].skill))
            .collect();
        let stf = start_params(cfg, &base);
        if cfg.stg && DatasetKind::of_library(&lib) == DatasetKind::ParaHome {
            bail!(
                "train --stg: ParaHome has no Stitched Trajectory Graph (Table 7); leave --stg off"
            );
        }
        let edges = if cfg.stg {
            crate::table::stg::load_edges(input, &lib, cfg.p_e)?
        } else {
            Vec::new()
        };
        let root = crate::dataset::data_root(data_root)?;
        let model = Model::for_skeleton(&root, lib.skeleton)?;
        let first = &lib.clips[clips[0]];
        for &c in &clips {
            let row = &lib.clips[c];
            if row.objects != first.objects {
                bail!(
                    "train: clips `{}` (objects {:?}) and `{}` (objects {:?}) need different worlds; \
                     train them separately (train.skills)",
                    first.name,
                    first.objects,
                    row.name,
                    row.objects
                );
            }
        }
        let objects = training_objects(&first.objects, &root, cfg)?;
        let sim = training_sim(first.fps as f64, cfg);
        let fps = first.fps as f64;
        let mut lib = lib;
        let hands = reference_hands(&mut lib, &clips, &model, &objects, cfg)?;
        let flights = reference_flights(&mut lib, &clips, &model, &objects, &sim, cfg)?;
        let ball_hands = ball_hands(&lib, &clips, &model, &objects, cfg)?;
        let (lib, edges) = if cfg.seam_leave_search_s > 0.0 {
            leave_early(lib, edges, &clips, cfg, fps)
        } else {
            (lib, edges)
        };
        let (seams, min_loop) =
            crate::augment::seam::training_seams(&lib, cfg.seam_min_loop_s, fps);
        let seam_pool = match cfg.seam_match {
            SeamMatch::Simulation => SeamPool::new(&lib, min_loop),
            SeamMatch::Reference => SeamPool::default(),
        };
        Ok(Setup {
            seams,
            seam_pool,
            hands,
            flights,
            ball_hands,
            fk: stf_cfg.fk,
            lib,
            edges,
            model,
            objects,
            sim,
            stf,
            ats_params,
            clips,
        })
    }

    /// The trained skills, each once, in the library's clip order.
    pub fn skills(&self) -> Vec<String> {
        self.lib
            .skills()
            .into_iter()
            .filter(|sk| self.clips.iter().any(|c| self.lib.clips[*c].skill == *sk))
            .collect()
    }
}

/// The objects `names` (from the data root `root`) as training simulates
/// them: with `cfg`'s `object_density`, `ball_inertia` and
/// `object_angular_damping`.
///
/// # Errors
/// An object that cannot be loaded; `train.ball_inertia = "shell"` without
/// a ball among them.
pub fn training_objects(
    names: &[String],
    root: &Path,
    cfg: &TrainConfig,
) -> Result<Vec<crate::sim::ObjectSpec>> {
    let mut objects = objects::load_all(names, root)?;
    objects::set_density(&mut objects, cfg.object_density.map(|d| d as f32));
    if cfg.ball_inertia != objects::BallInertia::Solid
        && !objects.iter().any(|o| o.sphere_mass_properties().is_some())
    {
        bail!(
            "train.ball_inertia = \"shell\": the training clips' objects ({names:?}) have no \
             ball; set it to \"solid\""
        );
    }
    objects::set_ball_inertia(&mut objects, cfg.ball_inertia);
    objects::set_angular_damping(&mut objects, cfg.object_angular_damping.map(|d| d as f32));
    Ok(objects)
}

/// The simulation options training uses for clips at `fps` frames per
/// second under `cfg` (its `pd_stiffness_scale` and `contact_recycling`).
pub fn training_sim(fps: f64, cfg: &TrainConfig) -> SimOptions {
    SimOptions {
        pd_stiffness_scale: cfg.pd_stiffness_scale as f32,
        contact_recycling: cfg.contact_recycling,
        ..SimOptions::for_fps(fps)
    }
}

/// The names of `clips` in `lib`, comma-separated (for the set-up's
/// errors).
fn clip_names(lib: &MotionLib, clips: &[usize]) -> String {
    clips
        .iter()
        .map(|&c| lib.clips[c].name.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

/// With `train.reference_hand = "on-ball"`, put the pushing hand of every
/// push window of `clips` on top of its ball
/// ([`crate::sim::hand_path::repair_hands`], the push search's window
/// settings) and return the windows repaired; nothing otherwise.
///
/// # Errors
/// The setting on while the clips have no ball or no push window, naming
/// `train.reference_hand`; as [`crate::sim::hand_path::repair_hands`].
pub fn reference_hands(
    lib: &mut MotionLib,
    clips: &[usize],
    model: &Model,
    objects: &[crate::sim::ObjectSpec],
    cfg: &TrainConfig,
) -> Result<Vec<crate::sim::hand_path::HandRepair>> {
    use crate::sim::hand_path::{repair_hands, ReferenceHand, BLEND_S};
    if cfg.reference_hand == ReferenceHand::Captured {
        return Ok(Vec::new());
    }
    if objects.first().is_none_or(|o| o.name != "ball") {
        bail!(
            "train.reference_hand = \"on-ball\": the training clips ({}) have no ball; set it \
             to \"captured\"",
            clip_names(lib, clips)
        );
    }
    let push = crate::sim::push::PushConfig::default();
    let hands = repair_hands(
        lib,
        clips,
        model,
        push.hand_radius,
        push.min_frames,
        BLEND_S,
    )?;
    if hands.is_empty() {
        bail!(
            "train.reference_hand = \"on-ball\": no push window in the training clips ({}) (a \
             ball descending with a hand body within {} m of it for {} frames), so the \
             reference would stay the captured one; set it to \"captured\"",
            clip_names(lib, clips),
            push.hand_radius,
            push.min_frames
        );
    }
    Ok(hands)
}

/// With `train.hand_follows_ball`, the push windows of `clips` whose
/// hand follows the simulated ball online
/// ([`crate::sim::hand_path::ball_hands`], the push search's window
/// settings, found on the clips as `train.reference_hand` left them,
/// reaching `train.hand_follows_ball_reach` at most); nothing otherwise.
///
/// # Errors
/// The setting on while the clips have no ball or no push window, naming
/// `train.hand_follows_ball`; as [`crate::sim::hand_path::ball_hands`].
pub fn ball_hands(
    lib: &MotionLib,
    clips: &[usize],
    model: &Model,
    objects: &[crate::sim::ObjectSpec],
    cfg: &TrainConfig,
) -> Result<Vec<crate::sim::hand_path::BallHand>> {
    if !cfg.hand_follows_ball {
        return Ok(Vec::new());
    }
    let names = clip_names(lib, clips);
    if objects.first().is_none_or(|o| o.name != "ball") {
        bail!(
            "train.hand_follows_ball: the training clips ({names}) have no ball; set it to false"
        );
    }
    let push = crate::sim::push::PushConfig::default();
    let mut hands = crate::sim::hand_path::ball_hands(
        lib,
        clips,
        model,
        push.hand_radius,
        push.min_frames,
        crate::sim::hand_path::BLEND_S,
        cfg.hand_follows_ball_from,
    )?;
    for h in &mut hands {
        h.reach = cfg.hand_follows_ball_reach;
    }
    if hands.is_empty() {
        bail!(
            "train.hand_follows_ball: no push window in the training clips ({names}) (a ball \
             descending with a hand body within {} m of it for {} frames); set it to false",
            push.hand_radius,
            push.min_frames
        );
    }
    Ok(hands)
}

/// With `train.reference_ball = "simulated"`, replace the ball flights of
/// `clips` by simulated ones ([`crate::sim::ball_path::simulate_flights`]
/// in the physics of `model`, `objects` and `sim`, a hand within the push
/// search's 0.15 m holding the ball) and return them, applied or not;
/// nothing otherwise.
///
/// # Errors
/// The setting on while the clips have no ball, or none of their flights
/// could be simulated (none found, or none solved with its one bounce),
/// naming `train.reference_ball`; as
/// [`crate::sim::ball_path::simulate_flights`].
pub fn reference_flights(
    lib: &mut MotionLib,
    clips: &[usize],
    model: &Model,
    objects: &[crate::sim::ObjectSpec],
    sim: &SimOptions,
    cfg: &TrainConfig,
) -> Result<Vec<crate::sim::ball_path::Flight>> {
    use crate::sim::ball_path::ReferenceBall;
    if cfg.reference_ball == ReferenceBall::Captured {
        return Ok(Vec::new());
    }
    let names = clip_names(lib, clips);
    if objects.first().is_none_or(|o| o.name != "ball") {
        bail!(
            "train.reference_ball = \"simulated\": the training clips ({}) have no ball; set it \
             to \"captured\"",
            names
        );
    }
    let scene = crate::sim::push::Scene {
        model,
        objects,
        opts: sim,
    };
    let radius = crate::sim::push::PushConfig::default().hand_radius;
    let flights = crate::sim::ball_path::simulate_flights(lib, clips, scene, radius)?;
    if !flights.iter().any(|f| f.applied) {
        bail!(
            "train.reference_ball = \"simulated\": no flight of the training clips ({}) could be \
             simulated ({} found: a release from a hand, a bounce, the hand on the ball again; \
             none solved within {} m with its one bounce), so the reference would stay the \
             captured one; set it to \"captured\"",
            names,
            flights.len(),
            crate::sim::ball_path::MISS_TOLERANCE
        );
    }
    Ok(flights)
}

/// `lib` with each trained clip of `clips` cut after the frame at which
/// training leaves it ([`crate::augment::seam::cut_at_leave_frames`]
/// within `cfg.seam_leave_search_s` of its end, at `fps`), and the STG
/// edges that still fit the cut clips.
fn leave_early(
    mut lib: MotionLib,
    edges: Vec<crate::augment::stg::Edge>,
    clips: &[usize],
    cfg: &TrainConfig,
    fps: f64,
) -> (MotionLib, Vec<crate::augment::stg::Edge>) {
    crate::augment::seam::cut_at_leave_frames(
        &mut lib,
        clips,
        cfg.seam_min_loop_s,
        cfg.seam_leave_search_s,
        fps,
    );
    let fits = |c: u32, f: u32| (f as usize) < lib.frames[c as usize].frames;
    let edges = edges
        .into_iter()
        .filter(|e| fits(e.src_clip, e.src_frame) && fits(e.dst_clip, e.dst_frame))
        .collect();
    (lib, edges)
}

/// The STF parameters of `cfg`'s switches over the recipe's `base`.
pub fn start_params(cfg: &TrainConfig, base: &StfParams) -> StfParams {
    let mut stf = base.clone();
    stf.p_e = if cfg.stg { cfg.p_e } else { 0.0 };
    stf.p_n = if cfg.nsi || cfg.stf { cfg.p_n } else { 0.0 };
    stf.horizon = cfg.episode_length;
    if cfg.nsi && !cfg.stf {
        // ε-NSI follows the centroid's clip: no connection, so no start is
        // given up for lack of one (τ only decides STF connections)
        stf.tau = 0.0;
    }
    stf
}

/// Build the training environment of `setup` with `n` worlds; `pushes`
/// are the feed-forward push offsets of `train.push_feed_forward`
/// ([`searched_pushes`]; empty when off).
///
/// # Errors
/// As [`HumanoidEnv::new`].
pub fn environment<'a>(
    s: &'a Setup,
    cfg: &TrainConfig,
    he: Option<HeRuntime>,
    n: usize,
    pushes: &[PushOffset],
    rng: &mut ChaCha8Rng,
) -> Result<HumanoidEnv<'a>> {
    let env_cfg = EnvConfig {
        early_termination: cfg.early_termination,
        fall_height: cfg.fall_height,
        collapse_reward: cfg.collapse_reward,
        masked_reward: cfg.masked_reward,
        reward: RewardOptions {
            contacts: cfg.contacts,
            contact_detect: cfg.contact_detect,
            contact_radius: cfg.contact_radius,
            root_rot: cfg.root_rot,
            smoothness: cfg.smoothness,
            weights: cfg.reward_weights,
        },
        continue_steps: if cfg.continuation {
            cfg.episode_length
        } else {
            0
        },
        term_key_distance: cfg.term_key_distance,
        term_object_distance: cfg.term_object_distance,
        term_object_error: cfg.term_object_error,
        fall_height_by_skill: cfg.fall_height_by_skill.clone(),
        seam_masked_min: cfg.seam_masked_min,
        residual_action: cfg.residual_action,
        reference_obs: cfg.reference_obs,
        feed_forward_lead: cfg.feed_forward_lead,
        velocity_feed_forward: cfg.velocity_feed_forward,
        velocity_feed_forward_joints: cfg.velocity_feed_forward_joints,
        residual_scale: cfg.residual_scale as f32,
        residual_scale_joints: cfg.residual_scale_joints,
        seam_blend_steps: cfg.seam_blend_steps,
        term_grace_steps: cfg.term_grace_steps,
        object_assist_band: cfg.object_assist_band as f32,
        seam_match: cfg.seam_match,
        ball_clock_frames: cfg.ball_clock_frames,
        sim_start_prob: cfg.sim_start_prob,
        sim_start_after: cfg.sim_start_after,
        energy_bonus: cfg.energy_bonus,
        energy_bonus_scale: cfg.energy_bonus_scale,
        object_floor: cfg.object_floor_at(0),
        push_feed_forward: pushes
            .iter()
            .map(|p| PushFeedForward {
                clip: p.clip,
                frames: p.window.start..p.window.release,
                offset: p.offset.clone(),
            })
            .collect(),
        nsi_follow: cfg.nsi && !cfg.stf,
        ats: cfg.ats,
        ats_params: s.ats_params,
        ats_update: cfg.ats_update,
        ..EnvConfig::training(cfg.method)
    };
    environment_with(s, &s.clips, s.stf.clone(), env_cfg, he, n, rng)
}

/// The action dimensions the policy's Gaussian explores and scores
/// ([`crate::rl::ppo::PpoConfig::free_dims`], `[J*3]`, three per joint of
/// `model`): every one but those of the joints that `residual_scale = 0`
/// leaves to the feed-forward pose (`train.residual_scale_joints`); empty
/// (all free) otherwise.
pub fn free_dims(cfg: &TrainConfig, model: &Model) -> Vec<bool> {
    if !(cfg.residual_action && cfg.residual_scale == 0.0) {
        return Vec::new();
    }
    cfg.residual_scale_joints
        .mask(model)
        .into_iter()
        .flat_map(|on| [!on; 3])
        .collect()
}

/// The feed-forward push offsets of `train.push_feed_forward` with
/// `train.push_objective` ([`searched_pushes`]; empty when off).
///
/// # Errors
/// As [`searched_pushes`].
pub fn feed_forward_pushes(s: &Setup, cfg: &TrainConfig, seed: u64) -> Result<Vec<PushOffset>> {
    searched_pushes(
        s,
        cfg.push_feed_forward,
        cfg.push_objective,
        seed,
        "push_feed_forward",
    )
}

/// The best offsets of every push window of `setup`'s training clips on
/// the joint `group` ([`crate::sim::push::push_offsets`], its default
/// search settings with `objective` (`train.push_objective`), `seed`);
/// empty for [`PushJoints::Off`]. The same
/// search serves `train.warm_start_push` and `train.push_feed_forward`.
///
/// # Errors
/// As [`crate::sim::push::push_offsets`], under `key`; a group that is on
/// while the training clips have no push window (no ball, or no hand
/// that pushes it down over a few frames), naming `train.key`.
pub fn searched_pushes(
    s: &Setup,
    group: PushJoints,
    objective: PushObjective,
    seed: u64,
    key: &str,
) -> Result<Vec<PushOffset>> {
    if group == PushJoints::Off {
        return Ok(Vec::new());
    }
    let pushes = crate::sim::push::push_offsets(
        &s.lib,
        &s.clips,
        crate::sim::push::Scene {
            model: &s.model,
            objects: &s.objects,
            opts: &s.sim,
        },
        &crate::sim::push::PushConfig {
            objective,
            ..Default::default()
        },
        group == PushJoints::Upper,
        seed,
    )
    .with_context(|| format!("train.{key}"))?;
    if pushes.is_empty() {
        bail!(
            "train.{key} = \"{}\": the training clips ({}) have no push window (a ball \
             descending with a hand on it over 3 frames or more from a start frame), so there \
             is nothing to add; set it to \"off\"",
            group.name(),
            s.clips
                .iter()
                .map(|&c| s.lib.clips[c].name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    Ok(pushes)
}

/// Build an environment of `n` worlds over `setup`'s library that starts
/// in `clips` with `stf`, with explicit settings (evaluation).
///
/// # Errors
/// As [`HumanoidEnv::new`].
pub fn environment_with<'a>(
    s: &'a Setup,
    clips: &[usize],
    stf: StfParams,
    env_cfg: EnvConfig,
    he: Option<HeRuntime>,
    n: usize,
    rng: &mut ChaCha8Rng,
) -> Result<HumanoidEnv<'a>> {
    let ats = Ats::for_clips(&s.lib, |c| clips.contains(&c));
    let weights = Weights::sm(DatasetKind::of_library(&s.lib));
    let mut sampler = StfSampler::new(&s.lib, &s.edges, weights);
    if s.fk && stf.p_n > 0.0 {
        sampler = sampler.with_model(s.model.clone());
    }
    // the online hand's windows come from the set-up, in training and in
    // evaluation alike
    let env_cfg = EnvConfig {
        ball_hand: s.ball_hands.clone(),
        ..env_cfg
    };
    HumanoidEnv::new(
        EnvParts {
            lib: &s.lib,
            sampler,
            stf,
            ats,
            model: s.model.clone(),
            objects: s.objects.clone(),
            sim: s.sim.clone(),
            cfg: env_cfg,
            he,
            seams: s.seams.clone(),
            seam_pool: s.seam_pool.clone(),
        },
        n,
        rng,
    )
}

/// Times the environment's steps (the simulation share of an iteration).
pub struct Timed<'e, E: VecEnv> {
    /// The wrapped environment.
    pub env: &'e mut E,
    /// Seconds spent in `step`.
    pub secs: f64,
}

impl<E: VecEnv> VecEnv for Timed<'_, E> {
    fn num_envs(&self) -> usize {
        self.env.num_envs()
    }
    fn obs_dim(&self) -> usize {
        self.env.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.env.act_dim()
    }
    fn observe(&self) -> Vec<f32> {
        self.env.observe()
    }
    fn step(&mut self, actions: &[f32], rng: &mut ChaCha8Rng) -> Result<StepResult> {
        let t = Instant::now();
        let r = self.env.step(actions, rng);
        self.secs += t.elapsed().as_secs_f64();
        r
    }
}

/// The history encoder of `cfg.he` (`None` without it) and the folder it was
/// read from: `train.he_dir`, else the run folder `input`, whose clips it
/// must have been pre-trained on.
///
/// # Errors
/// A missing or unreadable encoder, or one of the input folder pre-trained
/// on other clips than it holds now.
pub fn history_encoder(
    input: &Path,
    cfg: &TrainConfig,
    lib: &MotionLib,
    dev: &candle_core::Device,
) -> Result<Option<(HeRuntime, String)>> {
    if !cfg.he {
        return Ok(None);
    }
    let dir = if cfg.he_dir.is_empty() {
        input.to_path_buf()
    } else {
        PathBuf::from(&cfg.he_dir)
    };
    let enc = crate::nn::he::load(&dir, dev)?;
    // an encoder in the input folder was made from its clips; one from
    // another folder (`he_dir`) is the user's choice
    if cfg.he_dir.is_empty() {
        let id = crate::table::ingest_id(&input.join("clips.parquet"))?;
        if let Some(e) = enc
            .cfg
            .ingest_id
            .as_ref()
            .filter(|e| crate::table::ingest_ids_differ(e, &id))
        {
            bail!(
                "{}/he.config.json: the history encoder was pre-trained on other clips \
                 (ingest id {e}) than {} holds now ({id}): run `skillaug pretrain-he` again",
                dir.display(),
                input.display()
            );
        }
    }
    Ok(Some((HeRuntime::new(enc, lib)?, dir.display().to_string())))
}

/// Hash of the settings a checkpoint may be resumed with (all but
/// `train.samples`) and the seed.
///
/// # Errors
/// When the settings cannot be written as TOML.
pub fn settings_hash(cfg: &TrainConfig, stf_cfg: &StfConfig, seed: u64) -> Result<String> {
    let mut c = cfg.clone();
    c.samples = 0;
    let text = format!(
        "{}\n{}\nseed={seed}",
        toml::to_string(&c)?,
        toml::to_string(stf_cfg)?,
    );
    Ok(crate::config::hash_text(&text))
}

/// The settings a checkpoint may be resumed with, as TOML (`train`
/// without `samples`, `sample-stf`, `seed`), kept in the checkpoint so that
/// a refused resume can name what changed.
fn resume_settings(cfg: &TrainConfig, stf_cfg: &StfConfig, seed: u64) -> Result<String> {
    let mut c = cfg.clone();
    c.samples = 0;
    let mut t = toml::Table::new();
    t.insert("train".into(), toml::Value::try_from(&c)?);
    t.insert("sample-stf".into(), toml::Value::try_from(stf_cfg)?);
    t.insert("seed".into(), toml::Value::Integer(seed as i64));
    Ok(toml::to_string(&t)?)
}

/// `key = value` of every leaf of `v` under `prefix`.
fn leaves(prefix: &str, v: &toml::Value, out: &mut std::collections::BTreeMap<String, String>) {
    match v {
        toml::Value::Table(t) => {
            for (k, x) in t {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                leaves(&key, x, out);
            }
        }
        other => {
            out.insert(prefix.to_string(), other.to_string());
        }
    }
}

/// The keys whose values differ between two [`resume_settings`] texts, as
/// `key = now (the checkpoint: then)`, at most `max` of them.
fn changed_keys(then: &str, now: &str, max: usize) -> Vec<String> {
    let flat = |text: &str| {
        let mut m = std::collections::BTreeMap::new();
        if let Ok(t) = text.parse::<toml::Table>() {
            leaves("", &toml::Value::Table(t), &mut m);
        }
        m
    };
    let (a, b) = (flat(then), flat(now));
    let keys: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).collect();
    keys.into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .take(max)
        .map(|k| {
            let show = |v: Option<&String>| v.cloned().unwrap_or_else(|| "(not set)".into());
            format!(
                "{k} = {} (the checkpoint: {})",
                show(b.get(k)),
                show(a.get(k))
            )
        })
        .collect()
}

/// One rank's part of a checkpoint.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct RankState {
    rng_seed: Vec<u8>,
    rng_stream: u64,
    rng_word_pos: String,
    tracker: EpisodeTracker,
    episodes: Vec<EpisodeMeta>,
    /// The update's generator with `train.overlap_rollout` (absent
    /// without).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    update_rng: Option<RngState>,
    /// The rollout collected for the next update with
    /// `train.overlap_rollout` (its buffer goes to `pending.bin`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pending: Option<PendingMeta>,
    /// The states episodes may start from with `train.sim_start_prob`
    /// ([`HumanoidEnv::sim_pool`]; absent when empty).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    sim_pool: Vec<SimStart>,
    /// The pool slot the next state replaces once it is full.
    #[serde(default, skip_serializing_if = "super::config::is_zero_usize")]
    sim_next: usize,
}

/// A ChaCha8 generator's position.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct RngState {
    seed: Vec<u8>,
    stream: u64,
    word_pos: String,
}

impl RngState {
    fn of(r: &ChaCha8Rng) -> RngState {
        RngState {
            seed: r.get_seed().to_vec(),
            stream: r.get_stream(),
            word_pos: r.get_word_pos().to_string(),
        }
    }

    fn rng(&self) -> Result<ChaCha8Rng> {
        let mut seed32 = [0u8; 32];
        ensure!(self.seed.len() == 32, "checkpoint: RNG seed");
        seed32.copy_from_slice(&self.seed);
        let mut r = ChaCha8Rng::from_seed(seed32);
        r.set_stream(self.stream);
        r.set_word_pos(
            self.word_pos
                .parse::<u128>()
                .context("checkpoint: RNG position")?,
        );
        Ok(r)
    }
}

/// A collected rollout waiting for its update, without its buffer.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct PendingMeta {
    steps: usize,
    stats: EnvStats,
    returns: [f64; 2],
    sim_s: f64,
    collect_s: f64,
}

/// A collected rollout with what the iteration reports of it: the
/// environment's statistics and the finished episodes' return sum and
/// count, both combined over the ranks, and this rank's timings, s.
struct Collected {
    ro: super::Rollout,
    stats: EnvStats,
    returns: [f64; 2],
    sim_s: f64,
    collect_s: f64,
}

/// The ChaCha8 stream of rank `rank`'s update generator with
/// `train.overlap_rollout` (the rollout generators use streams 0..R).
pub fn update_stream(rank: usize) -> u64 {
    (1u64 << 32) + rank as u64
}

/// Collect `steps` steps of `env` with `actor`: the rollout, the seconds
/// spent in the environment's steps, and the whole collection's seconds.
///
/// # Errors
/// As [`collect`].
pub fn gather(
    actor: &Agent,
    env: &mut HumanoidEnv<'_>,
    steps: usize,
    tracker: &mut EpisodeTracker,
    rng: &mut ChaCha8Rng,
) -> Result<(super::Rollout, f64, f64)> {
    let t0 = Instant::now();
    let mut timed = Timed { env, secs: 0.0 };
    let ro = collect(actor, &mut timed, steps, tracker, rng)?;
    Ok((ro, timed.secs, t0.elapsed().as_secs_f64()))
}

/// Run `update` on this thread while [`gather`] collects `steps` steps of
/// `env` with `actor` on a second one (`train.overlap_rollout`): the
/// update's result and seconds, and the collection's. The collection is
/// joined before an error of either is returned.
///
/// # Errors
/// The update's or the collection's, or a panic of the rollout thread.
pub fn gather_during<U>(
    actor: &Agent,
    env: &mut HumanoidEnv<'_>,
    steps: usize,
    tracker: &mut EpisodeTracker,
    rng: &mut ChaCha8Rng,
    update: impl FnOnce() -> Result<U>,
) -> Result<(U, f64, (super::Rollout, f64, f64))> {
    std::thread::scope(|sc| {
        let h = sc.spawn(move || gather(actor, env, steps, tracker, rng));
        let t1 = Instant::now();
        let up = update();
        let update_s = t1.elapsed().as_secs_f64();
        let next = h
            .join()
            .map_err(|_| anyhow::anyhow!("train: the rollout thread panicked"))?;
        Ok((up?, update_s, next?))
    })
}

/// The trainer's state in a checkpoint beside the agent. Rank 0's part is
/// stored flat (the layout of one-process checkpoints); the other ranks'
/// parts follow in `ranks`.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct TrainerState {
    format: u32,
    /// Hash of the resolved settings (without `samples`).
    settings_hash: String,
    iteration: u64,
    samples: u64,
    /// Rank 0's generator, tracker and episodes, as fields of this object.
    #[serde(flatten)]
    rank0: RankState,
    ats: Vec<(usize, usize, f64, u64)>,
    metrics: Vec<MetricRow>,
    /// Ranks 1.. of a data-parallel run (absent for one process).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    ranks: Vec<RankState>,
    /// The settings behind `settings_hash` ([`resume_settings`]; absent in
    /// checkpoints of older versions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    settings: Option<String>,
}

/// A running episode without its actions (those go to `episodes.bin`).
#[derive(Clone, Debug, Serialize, Deserialize)]
struct EpisodeMeta {
    traj: crate::augment::stf::Trajectory,
    ats_key: (usize, usize),
    actions: usize,
    /// Object-assist strength of each step taken (`train.object_assist`;
    /// absent while none was assisted, as in older checkpoints).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    assists: Vec<f32>,
    /// Floor of the ball's reward factors at each step taken
    /// (`train.object_floor`; absent while none was set, as in older
    /// checkpoints).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    floors: Vec<f64>,
}

fn ckpt_dir(out: &Path) -> PathBuf {
    out.join("checkpoint")
}

/// The episodes file of rank `r` in a checkpoint folder.
fn episodes_file(r: usize) -> String {
    if r == 0 {
        "episodes.bin".into()
    } else {
        format!("episodes.{r}.bin")
    }
}

/// The pending rollout's file of rank `r` in a checkpoint folder.
fn pending_file(r: usize) -> String {
    if r == 0 {
        "pending.bin".into()
    } else {
        format!("pending.{r}.bin")
    }
}

fn actions_bytes(recs: &[EpisodeRecord]) -> Vec<u8> {
    let mut bytes = Vec::new();
    for r in recs {
        for a in &r.actions {
            bytes.extend_from_slice(&a.to_le_bytes());
        }
    }
    bytes
}

fn records_of(dir: &Path, file: &str, episodes: &[EpisodeMeta]) -> Result<Vec<EpisodeRecord>> {
    let path = dir.join(file);
    let bytes = std::fs::read(&path).with_context(|| format!("cannot read {}", path.display()))?;
    let total: usize = episodes.iter().map(|e| e.actions).sum();
    ensure!(
        bytes.len() == 4 * total,
        "{}: holds {} bytes, expected {}",
        path.display(),
        bytes.len(),
        4 * total
    );
    let mut at = 0;
    let mut recs = Vec::with_capacity(episodes.len());
    for e in episodes {
        let actions = bytes[4 * at..4 * (at + e.actions)]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        at += e.actions;
        recs.push(EpisodeRecord {
            traj: e.traj.clone(),
            ats_key: e.ats_key,
            actions,
            assists: e.assists.clone(),
            floors: e.floors.clone(),
        });
    }
    Ok(recs)
}

/// Refuse to start a fresh run in `out` when it holds a checkpoint (a
/// killed run that `--resume` would continue, or a finished one): starting
/// over would replace it.
///
/// # Errors
/// When `out/checkpoint/` (or `checkpoint.old/`, a swap cut short) holds a
/// checkpoint; the error says at which iteration and how to go on.
pub fn refuse_to_replace(out: &Path) -> Result<()> {
    for d in [ckpt_dir(out), out.join("checkpoint.old")] {
        let sp = d.join("state.json");
        if !sp.is_file() {
            continue;
        }
        let at = std::fs::read(&sp)
            .ok()
            .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
            .map(|v| {
                format!(
                    " at iteration {} ({} samples)",
                    v["iteration"], v["samples"]
                )
            })
            .unwrap_or_default();
        bail!(
            "{} holds a training checkpoint{at}: add --resume to continue that run, \
             or give another --out (or remove the folder) to start a new one",
            out.display()
        );
    }
    Ok(())
}

/// What [`load_checkpoint`] reads for one rank.
struct Loaded {
    agent: Agent,
    st: TrainerState,
    /// This rank's part of the state.
    part: RankState,
    /// This rank's running episodes.
    recs: Vec<EpisodeRecord>,
    /// This rank's pending rollout's file and bytes
    /// (`train.overlap_rollout`).
    pending: Option<(PathBuf, Vec<u8>)>,
}

/// Read the checkpoint of `out` (`checkpoint/`, or `checkpoint.old/` when
/// a swap was interrupted): the agent, the state and rank `rank`'s part.
fn load_checkpoint(
    out: &Path,
    dev: &candle_core::Device,
    rank: usize,
    ranks: usize,
) -> Result<Loaded> {
    let mut dir = ckpt_dir(out);
    if !dir.join("state.json").is_file() {
        dir = out.join("checkpoint.old");
    }
    ensure!(
        dir.join("state.json").is_file(),
        "--resume: no checkpoint in {} (train without --resume to start)",
        out.display()
    );
    let sp = dir.join("state.json");
    let st: TrainerState = serde_json::from_slice(&std::fs::read(&sp)?)
        .with_context(|| format!("{} is not a skillaug training checkpoint", sp.display()))?;
    ensure!(
        st.format == 1,
        "{}: checkpoint format {}",
        sp.display(),
        st.format
    );
    ensure!(
        st.ranks.len() + 1 == ranks,
        "--resume: the checkpoint in {} was written by {} rank(s), this run has {ranks}; \
         resume with the same number of ranks",
        out.display(),
        st.ranks.len() + 1
    );
    let agent = Agent::load(&dir.join("agent.safetensors"), dev)?;
    let part = if rank == 0 {
        st.rank0.clone()
    } else {
        st.ranks[rank - 1].clone()
    };
    let recs = records_of(&dir, &episodes_file(rank), &part.episodes)?;
    let pending = if part.pending.is_some() {
        let path = dir.join(pending_file(rank));
        let bytes = std::fs::read(&path)
            .with_context(|| format!("--resume: cannot read {}", path.display()))?;
        Some((path, bytes))
    } else {
        None
    };
    Ok(Loaded {
        agent,
        st,
        part,
        recs,
        pending,
    })
}

fn rng_of(part: &RankState) -> Result<ChaCha8Rng> {
    RngState {
        seed: part.rng_seed.clone(),
        stream: part.rng_stream,
        word_pos: part.rng_word_pos.clone(),
    }
    .rng()
}

/// What the behaviour cloning before PPO did ([`Agent::fit_mean`]).
#[derive(Clone, Debug, Default)]
pub struct WarmStart {
    /// The push windows whose frames fitted an offset
    /// (`train.warm_start_push`; empty when off).
    pub pushes: Vec<PushOffset>,
    /// States fitted (this rank's).
    pub states: usize,
    /// Mean squared action error before and after.
    pub mse: (f64, f64),
    /// Seconds taken.
    pub secs: f64,
}

/// What a training run is built from: the set-up, the settings, the seed,
/// the device and the ranks (one process: [`super::comm::Solo`]).
#[derive(Clone, Copy)]
pub struct TrainInputs<'a> {
    /// Library, worlds and start parameters.
    pub setup: &'a Setup,
    /// The `[train]` settings.
    pub cfg: &'a TrainConfig,
    /// The `[sample-stf]` settings.
    pub stf_cfg: &'a StfConfig,
    /// `--seed`.
    pub seed: u64,
    /// Where the networks live.
    pub dev: &'a candle_core::Device,
    /// The ranks.
    pub comm: &'a dyn Comm,
}

/// Where a run stands: episode tracker, metrics so far, iterations and
/// samples done.
struct Progress {
    tracker: EpisodeTracker,
    metrics: Vec<MetricRow>,
    iteration: u64,
    samples: u64,
    /// With `train.overlap_rollout`: the update's generator and the
    /// rollout collected for the next update (none before the first).
    update_rng: Option<ChaCha8Rng>,
    pending: Option<Collected>,
}

/// The PPO loop of `skillaug train` over one rank's share of the
/// environments (the whole run with [`super::comm::Solo`]).
pub struct Trainer<'a> {
    s: &'a Setup,
    cfg: TrainConfig,
    comm: &'a dyn Comm,
    env: HumanoidEnv<'a>,
    agent: Agent,
    rng: ChaCha8Rng,
    tracker: EpisodeTracker,
    metrics: Vec<MetricRow>,
    iteration: u64,
    samples: u64,
    hash: String,
    /// The `[sample-stf]` settings and the seed (for the checkpoint).
    stf_cfg: StfConfig,
    seed: u64,
    /// Every rank's ATS table after the last iteration (several ranks only).
    ats_base: Option<Ats>,
    /// The behaviour cloning before PPO of a fresh start.
    pub warm_start: Option<WarmStart>,
    /// The feed-forward push offsets (`train.push_feed_forward`; empty
    /// when off).
    pub push_ff: Vec<PushOffset>,
    /// With `train.overlap_rollout`: the update's own generator (the
    /// rollout keeps `rng`), the rollout the next update learns from, and
    /// the copy of the policy that collects while the agent updates.
    update_rng: Option<ChaCha8Rng>,
    pending: Option<Collected>,
    actor: Option<Agent>,
}

impl<'a> Trainer<'a> {
    /// The environments of this rank: `envs / ranks`.
    fn local_envs(cfg: &TrainConfig, comm: &dyn Comm) -> Result<usize> {
        let (n, r) = (cfg.envs(), comm.size());
        ensure!(
            n.is_multiple_of(r),
            "train: {n} environments do not split over {r} ranks; set train.num_envs to a multiple of {r}"
        );
        let mb = cfg.ppo_config().minibatch;
        ensure!(
            mb.is_multiple_of(r),
            "train: minibatch {mb} does not split over {r} ranks; set train.ppo.minibatch to a multiple of {r}"
        );
        Ok(n / r)
    }

    /// A fresh run: environments, agent (weights from `seed`, the same on
    /// every rank) and the warm start when `cfg.warm_start_epochs > 0`.
    ///
    /// # Errors
    /// Sizes that do not split over the ranks, or a failure to build the
    /// environment or the agent.
    pub fn start(inp: TrainInputs<'a>, he: Option<HeRuntime>) -> Result<Trainer<'a>> {
        let TrainInputs {
            setup: s,
            cfg,
            seed,
            comm,
            ..
        } = inp;
        let n = Self::local_envs(cfg, comm)?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        if comm.rank() > 0 {
            rng.set_stream(comm.rank() as u64);
        }
        let push_ff = feed_forward_pushes(s, cfg, seed)?;
        let env = environment(s, cfg, he, n, &push_ff, &mut rng)?;
        let mut ppo = cfg.ppo_config();
        if cfg.noise_correlation_joints != JointSet::All {
            // three action dimensions (an exp-map target) per joint
            ppo.noise_correlated_dims = cfg
                .noise_correlation_joints
                .mask(&s.model)
                .into_iter()
                .flat_map(|on| [on; 3])
                .collect();
        }
        ppo.free_dims = free_dims(cfg, &s.model);
        let mut agent = Agent::new(env.obs_dim(), env.act_dim(), &ppo, seed, inp.dev)?;
        let mut warm_start = None;
        if cfg.warm_start_epochs > 0 {
            let t = Instant::now();
            let pushes = searched_pushes(
                s,
                cfg.warm_start_push,
                cfg.push_objective,
                seed,
                "warm_start_push",
            )?;
            let (obs, targets) =
                env.warm_start_data(&s.clips, cfg.warm_start_copies, &pushes, &mut rng)?;
            let mse = agent.fit_mean(
                &obs,
                &targets,
                cfg.warm_start_epochs,
                // 512 for the presets; tiny test minibatches would make thousands of steps
                ppo.minibatch.clamp(256, 512),
                cfg.warm_start_lr,
                &mut rng,
                comm,
            )?;
            warm_start = Some(WarmStart {
                pushes,
                states: obs.len() / env.obs_dim(),
                mse,
                secs: t.elapsed().as_secs_f64(),
            });
        }
        let update_rng = cfg.overlap_rollout.then(|| {
            let mut r = ChaCha8Rng::seed_from_u64(seed);
            r.set_stream(update_stream(comm.rank()));
            r
        });
        let progress = Progress {
            tracker: EpisodeTracker::new(n),
            metrics: Vec::new(),
            iteration: 0,
            samples: 0,
            update_rng,
            pending: None,
        };
        let mut t = Self::assemble(inp, env, agent, rng, progress)?;
        t.warm_start = warm_start;
        t.push_ff = push_ff;
        Ok(t)
    }

    /// Continue the run checkpointed in `out` (same settings but
    /// `train.samples`, same seed and number of ranks).
    ///
    /// # Errors
    /// No checkpoint, settings or rank count that differ from the
    /// checkpoint's, or a checkpoint that does not fit the environment.
    pub fn resume(inp: TrainInputs<'a>, he: Option<HeRuntime>, out: &Path) -> Result<Trainer<'a>> {
        let TrainInputs {
            setup: s,
            cfg,
            stf_cfg,
            seed,
            comm,
            ..
        } = inp;
        let n = Self::local_envs(cfg, comm)?;
        let Loaded {
            agent,
            st,
            part,
            recs,
            pending: pending_bytes,
        } = load_checkpoint(out, inp.dev, comm.rank(), comm.size())?;
        if st.settings_hash != settings_hash(cfg, stf_cfg, seed)? {
            let now = resume_settings(cfg, stf_cfg, seed)?;
            let changed: String = st
                .settings
                .as_deref()
                .map(|then| changed_keys(then, &now, 8))
                .unwrap_or_default()
                .iter()
                .map(|c| format!("\n  {c}"))
                .collect();
            bail!(
                "--resume: the settings differ from those of the checkpoint in {} \
                 (only train.samples may change); start a new --out instead{changed}",
                out.display()
            );
        }
        let mut throwaway = ChaCha8Rng::seed_from_u64(seed);
        let push_ff = feed_forward_pushes(s, cfg, seed)?;
        let mut env = environment(s, cfg, he, n, &push_ff, &mut throwaway)?;
        env.restore(recs)?;
        env.set_sim_pool(part.sim_pool.clone(), part.sim_next)
            .with_context(|| format!("--resume: {}", out.display()))?;
        let mut ats = env.ats().clone();
        for (c, f, m, v) in &st.ats {
            ats.restore_stat(*c, *f, *m, *v);
        }
        env.set_ats(ats);
        ensure!(
            agent.obs_dim() == env.obs_dim() && agent.act_dim() == env.act_dim(),
            "--resume: the checkpoint's agent does not fit this environment"
        );
        ensure!(
            part.update_rng.is_some() == cfg.overlap_rollout,
            "--resume: the checkpoint in {} does not fit train.overlap_rollout = {}",
            out.display(),
            cfg.overlap_rollout
        );
        let pending = match (&part.pending, pending_bytes) {
            (Some(m), Some((path, b))) => Some(Collected {
                ro: super::Rollout::from_le_bytes(n, env.obs_dim(), env.act_dim(), m.steps, &b)
                    .with_context(|| {
                        format!(
                            "--resume: {} is damaged (restore the checkpoint, or start a new --out)",
                            path.display()
                        )
                    })?,
                stats: m.stats.clone(),
                returns: m.returns,
                sim_s: m.sim_s,
                collect_s: m.collect_s,
            }),
            _ => None,
        };
        let progress = Progress {
            tracker: part.tracker.clone(),
            metrics: st.metrics,
            iteration: st.iteration,
            samples: st.samples,
            update_rng: part.update_rng.as_ref().map(RngState::rng).transpose()?,
            pending,
        };
        let mut t = Self::assemble(inp, env, agent, rng_of(&part)?, progress)?;
        t.push_ff = push_ff;
        Ok(t)
    }

    /// The trainer of a fresh or resumed run: the environment's statistics
    /// and ATS records so far dropped, the ranks' ATS tables and weights
    /// checked alike.
    fn assemble(
        inp: TrainInputs<'a>,
        mut env: HumanoidEnv<'a>,
        agent: Agent,
        rng: ChaCha8Rng,
        progress: Progress,
    ) -> Result<Trainer<'a>> {
        env.take_stats();
        env.take_ats_log();
        let ats_base = (inp.comm.size() > 1).then(|| env.ats().clone());
        let t = Trainer {
            s: inp.setup,
            cfg: inp.cfg.clone(),
            comm: inp.comm,
            env,
            agent,
            rng,
            tracker: progress.tracker,
            metrics: progress.metrics,
            iteration: progress.iteration,
            samples: progress.samples,
            hash: settings_hash(inp.cfg, inp.stf_cfg, inp.seed)?,
            stf_cfg: inp.stf_cfg.clone(),
            seed: inp.seed,
            ats_base,
            warm_start: None,
            push_ff: Vec::new(),
            update_rng: progress.update_rng,
            pending: progress.pending,
            actor: None,
        };
        t.check_weights()?;
        Ok(t)
    }

    /// Fail when the ranks' weights differ (never with one rank).
    fn check_weights(&self) -> Result<()> {
        if self.comm.size() == 1 {
            return Ok(());
        }
        let w = self.agent.weights()?;
        let h = fingerprint(w.iter().map(|(_, v)| v.as_slice()));
        self.comm.check_identical(
            h,
            &format!("the weights after iteration {}", self.iteration),
        )
    }

    /// The agent.
    pub fn agent(&self) -> &Agent {
        &self.agent
    }

    /// The environment of this rank.
    pub fn env(&self) -> &HumanoidEnv<'a> {
        &self.env
    }

    /// One line describing the run (method, skills, sizes, networks,
    /// switches, ranks, and where a resumed run continues), as `skillaug
    /// train` prints it before the first iteration.
    pub fn describe(&self, resumed: bool) -> String {
        let cfg = &self.cfg;
        let ppo = self.agent.config();
        format!(
            "train: {:?} on {} ({} clips), {} envs x {} steps{}, obs {} act {}, nets {:?}, lr {}, switches nsi={} stg={} stf={} ats={} he={}{}",
            cfg.method,
            self.s.skills().join(", "),
            self.s.clips.len(),
            cfg.envs(),
            cfg.steps(),
            if self.comm.size() > 1 {
                format!(" over {} ranks", self.comm.size())
            } else {
                String::new()
            },
            self.env.obs_dim(),
            self.env.act_dim(),
            ppo.hidden,
            ppo.lr,
            cfg.nsi,
            cfg.stg,
            cfg.stf,
            cfg.ats,
            cfg.he,
            if resumed {
                format!(
                    ", resumed at iteration {} ({} samples)",
                    self.iteration, self.samples
                )
            } else {
                String::new()
            }
        ) + &self.options()
    }

    /// The tracking options that are on, as `, residual_action ...` (empty
    /// when none is), with a note where one has no effect.
    fn options(&self) -> String {
        let cfg = &self.cfg;
        let mut on = Vec::new();
        if cfg.residual_action {
            on.push("residual_action".to_string());
        }
        if cfg.reference_obs {
            on.push("reference_obs".to_string());
        }
        if cfg.feed_forward_lead != 0.0 {
            let idle = !cfg.residual_action && cfg.warm_start_epochs == 0;
            on.push(format!(
                "feed_forward_lead={}{}",
                cfg.feed_forward_lead,
                if idle {
                    " (no effect: no residual actions, no warm start)"
                } else {
                    ""
                }
            ));
        }
        if cfg.velocity_feed_forward {
            on.push(format!(
                "velocity_feed_forward{}{}",
                if cfg.velocity_feed_forward_joints == JointSet::Arms {
                    " (arms)"
                } else {
                    ""
                },
                if cfg.residual_action {
                    ""
                } else {
                    " (no effect: no residual actions)"
                }
            ));
        }
        if cfg.residual_scale != 1.0 {
            on.push(format!(
                "residual_scale={}{}",
                cfg.residual_scale,
                match cfg.residual_scale_joints {
                    JointSet::All => String::new(),
                    j if cfg.residual_scale == 0.0 =>
                        format!(
                        " ({}: the feed-forward pose alone, {} action values out of the policy's \
                         Gaussian)",
                        j.name(),
                        free_dims(cfg, &self.s.model).iter().filter(|&&f| !f).count()
                    ),
                    j => format!(" ({})", j.name()),
                }
            ));
        }
        if cfg.velocity_feed_forward_joints != JointSet::All && !cfg.velocity_feed_forward {
            on.push(
                "velocity_feed_forward_joints (no effect: velocity_feed_forward is off)"
                    .to_string(),
            );
        }
        if cfg.term_grace_steps > 0 {
            let idle = !cfg.continuation || !cfg.early_termination || cfg.term_key_distance <= 0.0;
            on.push(format!(
                "term_grace_steps={}{}",
                cfg.term_grace_steps,
                if idle {
                    " (no effect: needs continuation and the key-point rule)"
                } else {
                    ""
                }
            ));
        }
        if cfg.seam_blend_steps > 0 {
            on.push(format!(
                "seam_blend_steps={}{}",
                cfg.seam_blend_steps,
                if cfg.continuation {
                    ""
                } else {
                    " (no effect: continuation off)"
                }
            ));
        }
        if cfg.noise_correlation_joints != JointSet::All {
            on.push(format!(
                "noise_correlation_joints={}{}",
                cfg.noise_correlation_joints.name(),
                if cfg.ppo_config().noise_correlation > 0.0 {
                    ""
                } else {
                    " (no effect: ppo.noise_correlation is 0)"
                }
            ));
        }
        if cfg.seam_match == SeamMatch::Simulation {
            on.push(format!(
                "seam_match=simulation (seams matched to the simulated state){}",
                if cfg.continuation {
                    ""
                } else {
                    " (no effect: continuation off)"
                }
            ));
        }
        if cfg.object_assist > 0.0 {
            on.push(format!(
                "object_assist={} fading to 0 over {} samples{}",
                cfg.object_assist,
                cfg.object_assist_samples,
                if cfg.object_assist_band > 0.0 {
                    format!(", dead band {} m", cfg.object_assist_band)
                } else {
                    String::new()
                }
            ));
        }
        if cfg.warm_start_push != PushJoints::Off {
            on.push(format!(
                "warm_start_push={} (push windows' searched offsets in the warm start{})",
                cfg.warm_start_push.name(),
                if cfg.warm_start_epochs == 0 {
                    "; no effect: warm start off"
                } else {
                    ""
                }
            ));
        }
        if cfg.object_floor > 0.0 {
            on.push(format!(
                "object_floor={} (training reward r_b (f + (1 - f) r_o r_rel r_cg), f the floor{})",
                cfg.object_floor,
                if cfg.object_floor_samples > 0 {
                    format!(", fading to 0 over {} samples", cfg.object_floor_samples)
                } else {
                    String::new()
                }
            ));
        }
        if cfg.ball_inertia == crate::sim::objects::BallInertia::Shell {
            on.push("ball_inertia=shell (2/3 m r^2)".to_string());
        }
        if let Some(d) = cfg.object_angular_damping {
            on.push(format!("object_angular_damping={d} 1/s"));
        }
        if cfg.reference_hand != crate::sim::hand_path::ReferenceHand::Captured {
            on.push(format!(
                "reference_hand={} (the pushing hand on top of its ball)",
                cfg.reference_hand.name()
            ));
        }
        if cfg.hand_follows_ball {
            on.push(format!(
                "hand_follows_ball from the {}, reaching {} m at most (the pushing hand's \
                 targets on the simulated ball)",
                cfg.hand_follows_ball_from.name(),
                cfg.hand_follows_ball_reach
            ));
        }
        if !cfg.contact_recycling {
            on.push(
                "contact_recycling off (every contact recomputed at every physics step)".into(),
            );
        }
        if cfg.reference_ball != crate::sim::ball_path::ReferenceBall::Captured {
            on.push(format!(
                "reference_ball={} (flights from release to catch simulated)",
                cfg.reference_ball.name()
            ));
        }
        if cfg.push_feed_forward != PushJoints::Off {
            on.push(format!(
                "push_feed_forward={} (push windows' searched offsets in the feed-forward targets)",
                cfg.push_feed_forward.name()
            ));
        }
        if cfg.push_objective != PushObjective::Ball {
            on.push(format!(
                "push_objective={} (the push search's objective)",
                cfg.push_objective.name()
            ));
        }
        if cfg.overlap_rollout {
            on.push("overlap_rollout (rollouts by the policy of one update earlier)".to_string());
        }
        if on.is_empty() {
            String::new()
        } else {
            format!(", {}", on.join(", "))
        }
    }

    /// Iterations done.
    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    /// Samples learnt from by all ranks so far (with
    /// `train.overlap_rollout` one more batch has been simulated: the
    /// pending rollout).
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// One row per iteration so far.
    pub fn metrics(&self) -> &[MetricRow] {
        &self.metrics
    }

    /// Whether `train.samples` have been learnt from.
    pub fn done(&self) -> bool {
        self.samples >= self.cfg.samples
    }

    /// Sum `local` over the ranks (rank order), the same on every rank.
    fn rank_stats(&self, local: EnvStats) -> Result<EnvStats> {
        if self.comm.size() == 1 {
            return Ok(local);
        }
        let mut all = EnvStats::default();
        for b in self.comm.all_gather(&serde_json::to_vec(&local)?)? {
            let st: EnvStats = serde_json::from_slice(&b).context("statistics of another rank")?;
            all.add(&st);
        }
        Ok(all)
    }

    /// Collect one batch, update the agent and return the iteration's
    /// metrics (every rank's, combined). With `train.overlap_rollout` the
    /// update learns from the batch collected during the previous call
    /// (by the policy before that call's update: one update behind the
    /// policy this update starts from; the first call collects its own), the
    /// metrics are those of that batch, and the next batch is collected
    /// meanwhile ([`Trainer::samples`] counts the batches learnt from).
    ///
    /// # Errors
    /// A failure of the environment, the update, a collective, or ranks
    /// whose weights differ after the update.
    pub fn iterate(&mut self) -> Result<&MetricRow> {
        let n = self.env.num_envs();
        let steps = self.cfg.steps();
        let critic_only = self.iteration < self.cfg.critic_warmup_iters;
        // every rollout collected in this call, the overlapped one
        // included, gets the assist of the samples learnt so far
        let assist = self.cfg.object_assist_at(self.samples) as f32;
        self.env.set_object_assist(assist);
        self.env
            .set_object_floor(self.cfg.object_floor_at(self.samples));
        let t0 = Instant::now();
        let (c, up, update_s) = if self.cfg.overlap_rollout {
            self.overlapped(critic_only)?
        } else {
            let c = self.collect_now()?;
            let t1 = Instant::now();
            let up = self
                .agent
                .update_with(&c.ro, &mut self.rng, critic_only, self.comm)?;
            (c, up, t1.elapsed().as_secs_f64())
        };
        let (st, rs, sim_s, collect_s) = (c.stats, c.returns, c.sim_s, c.collect_s);
        let total_s = t0.elapsed().as_secs_f64();
        self.iteration += 1;
        self.check_weights()?;
        let batch = (n * steps * self.comm.size()) as u64;
        self.samples += batch;
        let mean_return = if rs[1] == 0.0 {
            f64::NAN
        } else {
            rs[0] / rs[1]
        };
        // start fractions are NaN when no episode started in the iteration
        self.metrics.push(MetricRow {
            iteration: self.iteration,
            samples: self.samples,
            metrics: Metrics {
                mean_reward: st.mean_reward(),
                mean_sm_reward: st.mean_sm(),
                fall_rate: st.fall_rate(),
                episodes: st.episodes as f64,
                mean_episode_length: st.mean_length(),
                mean_return,
                masked_frac: st.masked as f64 / st.steps.max(1) as f64,
                stg_start_frac: st.starts.stg_frac(),
                noised_start_frac: st.starts.noised_frac(),
                mean_n_masked: st.n_masked_sum as f64 / st.start_count() as f64,
                policy_loss: up.policy_loss,
                value_loss: up.value_loss,
                bounds_loss: up.bounds_loss,
                clip_frac: up.clip_frac,
                approx_kl: up.approx_kl,
                lr: up.lr,
                mean_sm_body: st.mean_sm_factor(0),
                mean_sm_object: st.mean_sm_factor(1),
                mean_sm_rel: st.mean_sm_factor(2),
                mean_sm_contact: st.mean_sm_factor(3),
                lost_rate: st.lost_rate(),
                lost_object_rate: st.lost_object_rate(),
                sim_start_frac: if st.start_count() + st.sim_starts > 0 {
                    st.sim_starts as f64 / (st.start_count() + st.sim_starts) as f64
                } else {
                    f64::NAN
                },
                continued_frac: if st.episodes > 0 {
                    st.continuations as f64 / st.episodes as f64
                } else {
                    f64::NAN
                },
                samples_per_s: batch as f64 / total_s,
                sim_s,
                act_s: collect_s - sim_s,
                update_s,
            },
        });
        Ok(self.metrics.last().expect("a row was just pushed"))
    }

    /// Collect one rollout with the agent itself, then [`Trainer::settle`].
    fn collect_now(&mut self) -> Result<Collected> {
        let (ro, sim_s, collect_s) = gather(
            &self.agent,
            &mut self.env,
            self.cfg.steps(),
            &mut self.tracker,
            &mut self.rng,
        )?;
        self.settle(ro, sim_s, collect_s)
    }

    /// What follows a collection on the main thread: the environment's
    /// statistics and the finished episodes' returns combined over the
    /// ranks, and the ATS table refreshed (replayed from every rank's
    /// records with several ranks).
    fn settle(&mut self, ro: super::Rollout, sim_s: f64, collect_s: f64) -> Result<Collected> {
        let local = self.env.take_stats();
        let stats = self.rank_stats(local)?;
        let log = self.env.take_ats_log();
        if let Some(base) = self.ats_base.take() {
            let mut all = Vec::new();
            for b in self.comm.all_gather(&ats_bytes(&log))? {
                all.extend(ats_records(&b)?);
            }
            self.env.replay_ats(base, &all);
            self.ats_base = Some(self.env.ats().clone());
        } else {
            self.env.refresh_ats();
        }
        let finished = self.tracker.take();
        let mut returns = [finished.iter().sum::<f64>(), finished.len() as f64];
        self.comm.sum_f64(&mut returns)?;
        Ok(Collected {
            ro,
            stats,
            returns,
            sim_s,
            collect_s,
        })
    }

    /// One iteration with `train.overlap_rollout`: the update learns from
    /// the pending rollout (collected now if there is none, at the first
    /// iteration) while a second thread collects the next one with a copy
    /// of the policy from before this update. Only the main thread calls
    /// collectives; the rollout thread touches the environment, the
    /// tracker and the rollout generator alone, so the outputs do not
    /// depend on how the two threads interleave. Returns the rollout
    /// learnt from, the update's statistics and its seconds.
    fn overlapped(&mut self, critic_only: bool) -> Result<(Collected, super::UpdateStats, f64)> {
        let steps = self.cfg.steps();
        if self.pending.is_none() {
            self.pending = Some(self.collect_now()?);
        }
        let cur = self.pending.take().expect("a pending rollout");
        match &mut self.actor {
            Some(a) => self.agent.copy_into(a)?,
            None => self.actor = Some(self.agent.actor_copy()?),
        }
        let actor = self.actor.as_ref().expect("an actor");
        let urng = self
            .update_rng
            .as_mut()
            .context("train: overlap_rollout without the update's generator")?;
        let (agent, comm) = (&mut self.agent, self.comm);
        let (up, update_s, (ro, sim_s, collect_s)) = gather_during(
            actor,
            &mut self.env,
            steps,
            &mut self.tracker,
            &mut self.rng,
            || agent.update_with(&cur.ro, urng, critic_only, comm),
        )?;
        self.pending = Some(self.settle(ro, sim_s, collect_s)?);
        Ok((cur, up, update_s))
    }

    /// Write the checkpoint into `out/checkpoint/` (staged in
    /// `checkpoint.tmp/`, then swapped into place by
    /// [`crate::table::io::StagedDir`], which leaves `checkpoint.old/` when
    /// cut short between its renames). Collective: every rank sends its
    /// part and rank 0 writes.
    ///
    /// # Errors
    /// A collective or a write that fails.
    pub fn checkpoint(&self, out: &Path) -> Result<()> {
        let recs = self.env.snapshot();
        let part = RankState {
            rng_seed: self.rng.get_seed().to_vec(),
            rng_stream: self.rng.get_stream(),
            rng_word_pos: self.rng.get_word_pos().to_string(),
            tracker: self.tracker.clone(),
            episodes: recs
                .iter()
                .map(|r| EpisodeMeta {
                    traj: r.traj.clone(),
                    ats_key: r.ats_key,
                    actions: r.actions.len(),
                    assists: r.assists.clone(),
                    floors: r.floors.clone(),
                })
                .collect(),
            update_rng: self.update_rng.as_ref().map(RngState::of),
            pending: self.pending.as_ref().map(|c| PendingMeta {
                steps: c.ro.steps(),
                stats: c.stats.clone(),
                returns: c.returns,
                sim_s: c.sim_s,
                collect_s: c.collect_s,
            }),
            sim_pool: self.env.sim_pool().0.to_vec(),
            sim_next: self.env.sim_pool().1,
        };
        let mine = actions_bytes(&recs);
        let pending = match &self.pending {
            Some(c) => Some(c.ro.to_le_bytes()?),
            None => None,
        };
        if self.comm.size() == 1 {
            let pendings = pending.into_iter().collect();
            return self.write_checkpoint(out, part, Vec::new(), vec![mine], pendings);
        }
        let parts = self.comm.gather(&serde_json::to_vec(&part)?)?;
        let actions = self.comm.gather(&mine)?;
        // every rank has a pending rollout or none (the same settings);
        // they can pass MPI's 2 GiB per gather (about 16k environments in
        // all at 32 steps), so they go in rounds
        let pendings = match pending {
            Some(b) => super::comm::gather_large(self.comm, &b)?,
            None => Some(Vec::new()),
        };
        if let (Some(parts), Some(actions), Some(pendings)) = (parts, actions, pendings) {
            let others = parts[1..]
                .iter()
                .map(|b| serde_json::from_slice(b).context("checkpoint part of another rank"))
                .collect::<Result<Vec<RankState>>>()?;
            self.write_checkpoint(out, part, others, actions, pendings)?;
        }
        Ok(())
    }

    fn write_checkpoint(
        &self,
        out: &Path,
        part: RankState,
        others: Vec<RankState>,
        actions: Vec<Vec<u8>>,
        pendings: Vec<Vec<u8>>,
    ) -> Result<()> {
        let st = TrainerState {
            format: 1,
            settings_hash: self.hash.clone(),
            iteration: self.iteration,
            samples: self.samples,
            rank0: part,
            ats: self.env.ats().visited(),
            metrics: self.metrics.clone(),
            ranks: others,
            settings: Some(resume_settings(&self.cfg, &self.stf_cfg, self.seed)?),
        };
        let write = || -> Result<()> {
            let mut dir = StagedDir::new(&ckpt_dir(out))?;
            dir.with_staged("agent.safetensors", |staged, path| {
                self.agent.stage(staged, path)
            })?;
            for (r, bytes) in actions.iter().enumerate() {
                dir.bytes(&episodes_file(r), bytes)?;
            }
            for (r, bytes) in pendings.iter().enumerate() {
                dir.bytes(&pending_file(r), bytes)?;
            }
            dir.bytes("state.json", &serde_json::to_vec(&st)?)?;
            dir.commit()
        };
        write().context("checkpoint")
    }

    /// The metadata that `policy.meta.json` holds for the agent as it is.
    /// `he_dir` is where the history encoder was read from (`None` without
    /// `he`).
    pub fn policy_meta(&self, stf: &StfConfig, he_dir: Option<String>) -> PolicyMeta {
        let s = self.s;
        PolicyMeta {
            format: 1,
            dataset: s.lib.clips[0].dataset.clone(),
            skeleton: s.lib.skeleton.name().to_string(),
            skills: s.skills(),
            clips: s
                .clips
                .iter()
                .map(|c| s.lib.clips[*c].name.clone())
                .collect(),
            objects: s.lib.clips[s.clips[0]].objects.clone(),
            obs_dim: self.env.obs_dim(),
            act_dim: self.env.act_dim(),
            he_dir,
            train: self.cfg.clone(),
            stf: stf.clone(),
            iterations: self.iteration,
            samples: self.samples,
            ranks: self.comm.size(),
            push_feed_forward: self
                .push_ff
                .iter()
                .map(|p| PushOffsetMeta {
                    clip: s.lib.clips[p.clip].name.clone(),
                    start: p.window.start,
                    release: p.window.release,
                    offset: p.offset.clone(),
                })
                .collect(),
            reference_flights: flight_meta(&s.flights, &s.lib),
        }
    }
}

/// `flights` as `policy.meta.json` holds them (clips by name in `lib`).
pub fn flight_meta(
    flights: &[crate::sim::ball_path::Flight],
    lib: &MotionLib,
) -> Vec<crate::rl::config::FlightMeta> {
    flights
        .iter()
        .map(|f| crate::rl::config::FlightMeta {
            clip: lib.clips[f.clip].name.clone(),
            release: f.release,
            catch: f.catch,
            v_sim: f.v_sim,
            applied: f.applied,
        })
        .collect()
}

/// ATS records as bytes: (clip u32, frame u32, reward f64) each.
fn ats_bytes(log: &[(usize, usize, f64)]) -> Vec<u8> {
    let mut b = Vec::with_capacity(16 * log.len());
    for &(c, f, r) in log {
        b.extend_from_slice(&(c as u32).to_le_bytes());
        b.extend_from_slice(&(f as u32).to_le_bytes());
        b.extend_from_slice(&r.to_le_bytes());
    }
    b
}

fn ats_records(b: &[u8]) -> Result<Vec<(usize, usize, f64)>> {
    ensure!(
        b.len().is_multiple_of(16),
        "ATS records of another rank: {} bytes",
        b.len()
    );
    Ok(b.chunks_exact(16)
        .map(|c| {
            (
                u32::from_le_bytes(c[0..4].try_into().expect("4 bytes")) as usize,
                u32::from_le_bytes(c[4..8].try_into().expect("4 bytes")) as usize,
                f64::from_le_bytes(c[8..16].try_into().expect("8 bytes")),
            )
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_changed_setting_is_named() {
        let (a, mut b) = (TrainConfig::default(), TrainConfig::default());
        b.ppo.lr = Some(1e-3);
        b.samples = 99; // not a resume setting
        let stf = StfConfig::default();
        let then = resume_settings(&a, &stf, 1).unwrap();
        let now = resume_settings(&b, &stf, 1).unwrap();
        let c = changed_keys(&then, &now, 8);
        assert_eq!(c, vec!["train.ppo.lr = 0.001 (the checkpoint: (not set))"]);
        assert_eq!(
            changed_keys(&then, &resume_settings(&a, &stf, 2).unwrap(), 8),
            vec!["seed = 2 (the checkpoint: 1)"]
        );
        assert!(changed_keys(&then, &then, 8).is_empty());
    }

    #[test]
    fn ats_records_travel_exactly() {
        let log = vec![
            (3, 17, 0.125),
            (0, 0, f64::MIN_POSITIVE),
            (9, 4, -1.0 / 3.0),
        ];
        assert_eq!(ats_records(&ats_bytes(&log)).unwrap(), log);
        assert!(ats_records(&[0u8; 15]).is_err());
    }
}
