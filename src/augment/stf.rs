//! State Transition Field sampling (paper Sections 4.3 and 4.5, Eqs. 6-7,
//! Algorithm 1, Appendix B.4, Table 7; reference code: Ingrid789/SkillMimic-V2
//! `skillmimic/env/tasks/skillmimic1_rand.py` and
//! `skillmimic/utils/motion_data_handler.py`): the start state of an episode
//! and the reference it follows.
//!
//! One trajectory for target skill A ([`StfSampler::sample`]):
//! 1. ATS picks a clip of A (class weights, then clip weights; [`super::ats`]).
//! 2. **Centroid** (paper order, Algorithm 1): with probability p_e an
//!    external start, an STG edge of target skill A chosen uniformly, whose
//!    start is the source state moved onto the edge's target frame
//!    ([`Edge::aligned_start`]); otherwise a start frame k of the clip chosen
//!    by ATS (Eq. 8). A skill without edges always starts from its own frames.
//! 3. **ε-NSI**: with probability p_n the start is replaced by a state drawn
//!    from its ε-neighbourhood ([`perturb`]; per-group ε of Table 7 taken
//!    from the target class A, with per-class overrides: Getup, class 0, has
//!    ε_rootpos = ε_rootvel = 1.0 as in Table 7; the reference code enlarges
//!    the root height and rotation instead, `_init_with_random_noise` in
//!    `skillmimic1_rand.py`).
//! 4. **Connection** (Eq. 6): j = argmax S_k(ŝ, start) over the candidate
//!    frames ŝ of A (valid frames in [2, F - 2] of every clip of A, as
//!    `noisyinit_find_most_similarity_state` in `motion_data_handler.py`;
//!    [`Search::Clip`] restricts the search to the centroid's clip as the
//!    reference code does). No alignment: the start already lives in the
//!    target's coordinates (an RSI start is a frame of A, an STG start was
//!    moved onto its target frame). When the start has not been perturbed
//!    the centroid frame (RSI) or the edge's target frame (STG) is compared
//!    first and wins ties, so an unperturbed RSI start connects to itself
//!    with β = 1 exactly and N = 0.
//! 5. **Masked states**: N = [`super::n_masked`]\(β) (Eq. 20). When β <= τ
//!    there is no valid connection (B.4); the sampler then falls back to a
//!    plain reference start (the RSI centroid unperturbed, or an ATS frame of
//!    the clip for an STG start; β = 1, N = 0, `fallback = true`).
//!
//! **Steps** ([`Trajectory::steps`]): step 0 is the start state itself (the
//! state the simulator is reset to; no reference, no reward). With the
//! paper's Eq. 7 ([`Connect::Paper`], default) steps 1..=N are inserted masked
//! states s∅ (no reference, excluded from the reward) and steps N+1, N+2, ...
//! follow ŝ_j, ŝ_{j+1}, ... to the clip's last valid frame or the horizon
//! (`horizon` policy steps after step 0). A reference frame that is missing
//! in the data is also a masked step (it keeps its clip and frame). So an
//! unperturbed RSI start at frame k reads {ŝ_k, ŝ_k, ŝ_{k+1}, ...}: Eq. 7
//! taken literally asks the first step to reach ŝ_j even when the start is
//! already there. [`Connect::Reference`] is the reference code's indexing
//! (`skillmimic1_rand.py`: ts = max(progress - N, 0)): the start takes the
//! place of ŝ_j, so N = 0 continues with ŝ_{j+1} and N >= 1 inserts N - 1
//! masked states before ŝ_j. (Together with the reference's floor rule for N
//! this matches the paper's step count except for β > 0.5, where the code takes
//! no transition step at all.)
//!
//! **Order** ([`Order::Reference`], `skillmimic1_rand.py`): the code draws an
//! RSI frame first, then noise with p_n, and only for un-noised starts the STG
//! switch with p_e, so noise and switch never combine. Its switch picks an edge
//! whose target frame is the RSI frame when the graph has one (the
//! `--per-target` graph always does), else any edge of A.
//!
//! **Perturbation** ([`perturb`]): every component uniform in [-ε, ε]
//! (paper: a uniform box; [`Noise::Gaussian`] with σ = ε is the option, the
//! reference code uses Gaussians). Root position: all three components. Root
//! rotation: composed (in the world frame) with a random rotation vector
//! whose components lie within ε_rootrot, so the quaternion stays unit; the
//! root exp-map is recomputed from it, on the branch nearest the stored one.
//! Joints: each exp-map component. Velocities: added. Objects: position,
//! rotation (composed like the root), linear and angular velocity. Body
//! positions move rigidly with the root (translated by the root offset,
//! turned about the root by the root's rotation noise) and body velocities
//! by the root's velocity offset. With the humanoid model set
//! ([`StfSampler::with_model`], what `sample-stf` does by default) the body
//! positions then follow the joint noise through forward kinematics of the
//! MJCF ([`refresh_bodies`]); without it, joint noise does not move the
//! bodies.
//!
//! Pure code and deterministic for a given RNG: the stage gives each
//! trajectory its own ChaCha stream.

use super::ats::{start_frames, AtsWeights};
use super::stg::Edge;
use super::{n_masked, MaskRule};
use crate::motion::{quat, Kinematics, MotionLib, State};
use crate::reward::{self, Align, Weights};
use rand::Rng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Per-group neighbourhood radii ε (Table 7), in the units of each group
/// (m, m/s, rad, rad/s).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Eps {
    /// Root position, m.
    pub root_pos: f64,
    /// Root linear velocity, m/s.
    pub root_vel: f64,
    /// Root rotation, rad (per rotation-vector component).
    pub root_rot: f64,
    /// Root angular velocity, rad/s.
    pub root_rot_vel: f64,
    /// Joint exp-map components, rad.
    pub dof: f64,
    /// Joint exp-map velocities, rad/s.
    pub dof_vel: f64,
    /// Object position, m.
    pub obj_pos: f64,
    /// Object linear velocity, m/s.
    pub obj_vel: f64,
    /// Object rotation, rad (per rotation-vector component).
    pub obj_rot: f64,
    /// Object angular velocity, rad/s.
    pub obj_rot_vel: f64,
}

impl Eps {
    /// Every group the same radius.
    pub fn all(e: f64) -> Eps {
        Eps {
            root_pos: e,
            root_vel: e,
            root_rot: e,
            root_rot_vel: e,
            dof: e,
            dof_vel: e,
            obj_pos: e,
            obj_vel: e,
            obj_rot: e,
            obj_rot_vel: e,
        }
    }

    /// Table 7's Getup column: ε_rootpos = ε_rootvel = 1.0, the rest 0.1.
    pub fn getup() -> Eps {
        Eps {
            root_pos: 1.0,
            root_vel: 1.0,
            ..Eps::all(0.1)
        }
    }
}

impl Default for Eps {
    fn default() -> Self {
        Eps::all(0.1)
    }
}

/// Distribution of the neighbourhood noise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Noise {
    /// Uniform in [-ε, ε] per component (paper).
    #[default]
    Uniform,
    /// Gaussian with σ = ε per component (reference code).
    Gaussian,
}

/// Order of the switch and the noise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Order {
    /// Algorithm 1: external start with p_e, then noise with p_n on top.
    #[default]
    Paper,
    /// The reference code's order (Ingrid789/SkillMimic-V2
    /// `skillmimic/env/tasks/skillmimic1_rand.py`): noise with p_n, else
    /// switch with p_e (never both).
    Reference,
}

/// Where the reference resumes after the masked states.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Connect {
    /// Eq. 7: start, N masked, ŝ_j, ŝ_{j+1}, ...
    #[default]
    Paper,
    /// The reference code's indexing (Ingrid789/SkillMimic-V2
    /// `skillmimic/env/tasks/skillmimic1_rand.py`): the start stands for ŝ_j:
    /// N - 1 masked then ŝ_j (N >= 1), or ŝ_{j+1}, ... (N = 0).
    Reference,
}

/// Which reference frames Eq. 6 searches.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Search {
    /// Every clip of skill A (paper: all states of A).
    #[default]
    Skill,
    /// Only the centroid's clip (the edge's target clip for STG starts), as
    /// the reference code searches (Ingrid789/SkillMimic-V2
    /// `skillmimic/utils/motion_data_handler.py`,
    /// `noisyinit_find_most_similarity_state`).
    Clip,
}

/// STF settings (Table 7).
#[derive(Clone, Debug, PartialEq)]
pub struct StfParams {
    /// Probability of an external (STG) start.
    pub p_e: f64,
    /// Probability of replacing the start by a neighbour.
    pub p_n: f64,
    /// Neighbourhood radii.
    pub eps: Eps,
    /// Per-class radii replacing `eps` (default: class 0, Getup).
    pub eps_class: BTreeMap<u32, Eps>,
    /// Noise distribution.
    pub noise: Noise,
    /// Similarity threshold τ.
    pub tau: f64,
    /// Maximum masked states N_max.
    pub n_max: u32,
    /// Eq. 20 rule.
    pub mask_rule: MaskRule,
    /// Switch/noise order.
    pub order: Order,
    /// Reference indexing after the start.
    pub connect: Connect,
    /// Frames searched by Eq. 6.
    pub search: Search,
    /// Policy steps after the start at most (episode length T; 60).
    pub horizon: usize,
}

impl Default for StfParams {
    fn default() -> Self {
        StfParams {
            p_e: 0.1,
            p_n: 0.1,
            eps: Eps::default(),
            eps_class: BTreeMap::from([(0, Eps::getup())]),
            noise: Noise::Uniform,
            tau: 1e-10,
            n_max: 10,
            mask_rule: MaskRule::Paper,
            order: Order::Paper,
            connect: Connect::Paper,
            search: Search::Skill,
            horizon: 60,
        }
    }
}

impl StfParams {
    /// The radii of `class`.
    pub fn eps_for(&self, class: u32) -> &Eps {
        self.eps_class.get(&class).unwrap_or(&self.eps)
    }
}

/// Where the start state came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum StartKind {
    /// A frame of the target skill (reference state initialisation via ATS).
    Rsi,
    /// An external state through an STG edge.
    Stg,
}

/// A start's kind and whether it was drawn from the ε-neighbourhood: the
/// four start labels of the summaries and of `stf_samples.parquet`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StartLabel {
    /// A plain reference frame of the target skill.
    Rsi,
    /// Drawn around a reference frame of the target skill.
    RsiNoise,
    /// A plain external state through an STG edge.
    Stg,
    /// Drawn around an external state through an STG edge.
    StgNoise,
}

impl StartLabel {
    /// Every label, in the order of the summary's columns.
    pub const ALL: [StartLabel; 4] = [
        StartLabel::Rsi,
        StartLabel::RsiNoise,
        StartLabel::Stg,
        StartLabel::StgNoise,
    ];

    /// The label of a start of `kind`, `noised` or not.
    pub fn of(kind: StartKind, noised: bool) -> StartLabel {
        match (kind, noised) {
            (StartKind::Rsi, false) => StartLabel::Rsi,
            (StartKind::Rsi, true) => StartLabel::RsiNoise,
            (StartKind::Stg, false) => StartLabel::Stg,
            (StartKind::Stg, true) => StartLabel::StgNoise,
        }
    }

    /// "rsi", "rsi+noise", "stg" or "stg+noise".
    pub fn as_str(self) -> &'static str {
        match self {
            StartLabel::Rsi => "rsi",
            StartLabel::RsiNoise => "rsi+noise",
            StartLabel::Stg => "stg",
            StartLabel::StgNoise => "stg+noise",
        }
    }
}

/// One step of a sampled trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Step {
    /// No reward at this step: an inserted state s∅ or a missing reference frame.
    pub masked: bool,
    /// Clip of the reference frame (`None` for the start and inserted states).
    pub ref_clip: Option<u32>,
    /// Frame of the reference frame.
    pub ref_frame: Option<u32>,
}

impl Step {
    /// An inserted masked state s∅ (no reference at all).
    pub fn is_inserted(&self) -> bool {
        self.masked && self.ref_clip.is_none()
    }
}

/// A trajectory sampled from the STF.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Trajectory {
    /// Skill A.
    pub target_skill: String,
    /// Condition: the class of A.
    pub condition: u32,
    /// The state the episode starts in.
    pub start: State,
    /// Origin of the start.
    pub start_kind: StartKind,
    /// The start was drawn from the ε-neighbourhood of the centroid.
    pub noised: bool,
    /// β <= τ: the sampled start had no connection and was replaced by a plain reference start.
    pub fallback: bool,
    /// The centroid (before noise): the RSI frame of A, or the STG edge's source frame.
    pub centroid: (u32, u32),
    /// ŝ_j: the clip and frame the start connects to (Eq. 6). The trainer
    /// records the episode's mean reward for ATS here.
    pub connect: (u32, u32),
    /// S_k(ŝ_j, start).
    pub beta: f64,
    /// Masked states N (Eq. 20).
    pub n_masked: u32,
    /// Step 0 (the start) and one step per policy step.
    pub steps: Vec<Step>,
    /// The start is a state a training rollout reached, not a clip frame
    /// (`train.sim_start_prob`, [`crate::rl::humanoid::SimStart`]): its
    /// episode updates no ATS statistic. False in every STF sample.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub simulated: bool,
}

impl Trajectory {
    /// The start's kind and noise.
    pub fn start_label(&self) -> StartLabel {
        StartLabel::of(self.start_kind, self.noised)
    }

    /// "rsi", "stg", "rsi+noise" or "stg+noise" ([`StartLabel::as_str`]).
    pub fn kind_label(&self) -> &'static str {
        self.start_label().as_str()
    }

    /// Policy steps (rows after step 0).
    pub fn policy_steps(&self) -> usize {
        self.steps.len().saturating_sub(1)
    }
}

/// One draw of the noise for radius `e`.
fn draw<R: Rng>(e: f64, noise: Noise, rng: &mut R) -> f64 {
    match noise {
        Noise::Uniform => e * (2.0 * rng.random::<f64>() - 1.0),
        // one normal per two uniforms (the pair's second is not used)
        Noise::Gaussian => e * crate::random::normal_pair(rng).0,
    }
}

fn draw3<R: Rng>(e: f64, noise: Noise, rng: &mut R) -> [f64; 3] {
    [
        draw(e, noise, rng),
        draw(e, noise, rng),
        draw(e, noise, rng),
    ]
}

/// A state drawn from the ε-neighbourhood of `s` (see the module doc for what
/// each group does). Draw order: root rotation, root position, root linear
/// and angular velocity, joint exp-maps, joint velocities, then per object
/// position, rotation, linear and angular velocity.
pub fn perturb<R: Rng>(s: &State, eps: &Eps, noise: Noise, rng: &mut R) -> State {
    let mut o = s.clone();
    let dr = draw3(eps.root_rot, noise, rng);
    let dp = draw3(eps.root_pos, noise, rng);
    let dv = draw3(eps.root_vel, noise, rng);
    let dw = draw3(eps.root_rot_vel, noise, rng);
    let qd = quat::from_expmap(dr);
    let turned = dr != [0.0; 3];
    if turned {
        let q = quat::normalize(quat::mul(qd, s.root_rot.map(|v| v as f64)));
        o.root_rot = q.map(|v| v as f32);
        o.root_rot_expmap =
            quat::nearest_expmap(quat::to_expmap(q), s.root_rot_expmap).map(|v| v as f32);
    }
    let root = s.root_pos.map(|v| v as f64);
    for i in 0..3 {
        o.root_pos[i] = (root[i] + dp[i]) as f32;
        o.root_linvel[i] = (s.root_linvel[i] as f64 + dv[i]) as f32;
        o.root_angvel[i] = (s.root_angvel[i] as f64 + dw[i]) as f32;
    }
    // Bodies follow the root rigidly; with the humanoid model the sampler
    // then recomputes them by forward kinematics (refresh_bodies).
    for (b, v) in o
        .body_pos
        .chunks_exact_mut(3)
        .zip(o.body_vel.chunks_exact_mut(3))
    {
        let rel = [
            b[0] as f64 - root[0],
            b[1] as f64 - root[1],
            b[2] as f64 - root[2],
        ];
        let rel = if turned { quat::rotate(qd, rel) } else { rel };
        for i in 0..3 {
            b[i] = (root[i] + dp[i] + rel[i]) as f32;
            v[i] = (v[i] as f64 + dv[i]) as f32;
        }
    }
    for x in o.joint_rot.iter_mut() {
        *x = (*x as f64 + draw(eps.dof, noise, rng)) as f32;
    }
    for x in o.joint_vel.iter_mut() {
        *x = (*x as f64 + draw(eps.dof_vel, noise, rng)) as f32;
    }
    for k in 0..s.obj_pos.len() / 3 {
        let d = draw3(eps.obj_pos, noise, rng);
        let r = draw3(eps.obj_rot, noise, rng);
        let v = draw3(eps.obj_vel, noise, rng);
        let w = draw3(eps.obj_rot_vel, noise, rng);
        for i in 0..3 {
            o.obj_pos[3 * k + i] = (s.obj_pos[3 * k + i] as f64 + d[i]) as f32;
            o.obj_linvel[3 * k + i] = (s.obj_linvel[3 * k + i] as f64 + v[i]) as f32;
            o.obj_angvel[3 * k + i] = (s.obj_angvel[3 * k + i] as f64 + w[i]) as f32;
        }
        if r != [0.0; 3] {
            let q0: quat::Quat = std::array::from_fn(|i| s.obj_rot[4 * k + i] as f64);
            let q = quat::normalize(quat::mul(quat::from_expmap(r), q0));
            for (dst, v) in o.obj_rot[4 * k..4 * k + 4].iter_mut().zip(q) {
                *dst = v as f32;
            }
        }
    }
    o
}

/// Body positions of a perturbed state from forward kinematics:
/// `stored + FK(perturbed) - FK(original)`, so joint noise moves the bodies
/// while the stored capture positions (which differ from the model's FK by
/// 3-5 cm on BallPlay, `skillaug check-fk`) stay the baseline.
pub fn refresh_bodies(original: &State, perturbed: &mut State, model: &dyn Kinematics) {
    let before = model.body_positions(original.root_pos, original.root_rot, &original.joint_rot);
    let after = model.body_positions(perturbed.root_pos, perturbed.root_rot, &perturbed.joint_rot);
    for (k, b) in perturbed.body_pos.iter_mut().enumerate() {
        *b = original.body_pos[k] + (after[k] - before[k]);
    }
}

/// Samples trajectories from the STF of a motion library (precomputes the
/// candidate frames of Eq. 6 and groups the STG edges by target skill).
pub struct StfSampler<'a> {
    lib: &'a MotionLib,
    weights: Weights,
    /// Per clip: its Eq. 6 candidate frames and their states.
    cands: Vec<Vec<(usize, State)>>,
    /// Clips of each skill.
    skill_clips: BTreeMap<String, Vec<usize>>,
    /// STG edges by target skill (only those whose clips exist).
    edges: BTreeMap<String, Vec<Edge>>,
    /// The humanoid's forward kinematics, for perturbed starts.
    model: Option<Box<dyn Kinematics>>,
}

impl<'a> StfSampler<'a> {
    /// Use `model`'s forward kinematics for the body positions of perturbed
    /// starts (see [`refresh_bodies`]).
    pub fn with_model(mut self, model: impl Kinematics + 'static) -> Self {
        self.model = Some(Box::new(model));
        self
    }

    /// [`perturb`], then the body positions from forward kinematics when a
    /// model is set.
    fn perturb_fk<R: Rng>(&self, s: &State, eps: &Eps, noise: Noise, rng: &mut R) -> State {
        let mut o = perturb(s, eps, noise, rng);
        if let Some(m) = &self.model {
            refresh_bodies(s, &mut o, m.as_ref());
        }
        o
    }

    /// A sampler over `lib` with the STG `edges` (may be empty) and the
    /// similarity weights of the dataset ([`Weights::sm`]).
    pub fn new(lib: &'a MotionLib, edges: &[Edge], weights: Weights) -> StfSampler<'a> {
        let cands = lib
            .frames
            .iter()
            .enumerate()
            .map(|(c, cf)| {
                start_frames(cf)
                    .iter()
                    .enumerate()
                    .filter(|(_, ok)| **ok)
                    .filter_map(|(f, _)| Some((f, lib.state(c, f)?)))
                    .collect()
            })
            .collect();
        let skill_clips = lib
            .skills()
            .into_iter()
            .map(|s| (s.clone(), lib.clips_of(&s)))
            .collect();
        let n = lib.clips.len() as u32;
        let mut by: BTreeMap<String, Vec<Edge>> = BTreeMap::new();
        for e in edges.iter().filter(|e| e.src_clip < n && e.dst_clip < n) {
            by.entry(e.target_skill.clone())
                .or_default()
                .push(e.clone());
        }
        StfSampler {
            lib,
            weights,
            cands,
            skill_clips,
            edges: by,
            model: None,
        }
    }

    /// The STG edges of target skill `skill`.
    pub fn edges_of(&self, skill: &str) -> &[Edge] {
        self.edges.get(skill).map_or(&[], Vec::as_slice)
    }

    /// Sample one trajectory: ATS picks the clip (and so skill A), then
    /// [`StfSampler::sample_in_clip`]. `None` if no clip can start.
    pub fn sample<R: Rng>(
        &self,
        ats: &AtsWeights,
        p: &StfParams,
        rng: &mut R,
    ) -> Option<Trajectory> {
        let clip = ats.sample_clip(rng)?;
        self.sample_in_clip(clip, ats, p, rng)
    }

    /// `n` trajectories ([`StfSampler::sample`]) in parallel, trajectory
    /// `i` drawn from its own ChaCha8 stream `i` of `seed`: the same
    /// trajectories at any thread count. `None` if no clip can start.
    pub fn sample_many(
        &self,
        ats: &AtsWeights,
        p: &StfParams,
        n: usize,
        seed: u64,
    ) -> Option<Vec<Trajectory>> {
        use rand::SeedableRng;
        use rayon::prelude::*;
        (0..n)
            .into_par_iter()
            .map(|i| {
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
                rng.set_stream(i as u64);
                self.sample(ats, p, &mut rng)
            })
            .collect()
    }

    /// Sample one trajectory whose target skill is that of `clip` and whose
    /// RSI frames come from `clip` (by the ATS frame weights). `None` if the
    /// clip has no start frame.
    pub fn sample_in_clip<R: Rng>(
        &self,
        clip: usize,
        ats: &AtsWeights,
        p: &StfParams,
        rng: &mut R,
    ) -> Option<Trajectory> {
        let lib = self.lib;
        let row = lib.clips.get(clip)?;
        let skill = &row.skill;
        let class = row.class as u32;
        let edges = self.edges_of(skill);
        let eps = p.eps_for(class);
        let rsi = |rng: &mut R| -> Option<(usize, State)> {
            let f = ats.sample_frame(clip, rng)?;
            Some((f, lib.state(clip, f)?))
        };
        let rsi_start = |f: usize, s: State| (s, StartKind::Rsi, (clip, f), (clip, f));
        // (start, kind, centroid, hint = the frame an unperturbed start stands for)
        let (start, kind, centroid, hint, noised) = match p.order {
            Order::Paper => {
                let switch = rng.random::<f64>() < p.p_e && !edges.is_empty();
                let stg = if switch {
                    let e = &edges[rng.random_range(0..edges.len())];
                    e.aligned_start(lib).map(|s| {
                        let src = (e.src_clip as usize, e.src_frame as usize);
                        (
                            s,
                            StartKind::Stg,
                            src,
                            (e.dst_clip as usize, e.dst_frame as usize),
                        )
                    })
                } else {
                    None
                };
                let (s, kind, centroid, hint) = match stg {
                    Some(x) => x,
                    None => {
                        let (f, s) = rsi(&mut *rng)?;
                        rsi_start(f, s)
                    }
                };
                let noised = rng.random::<f64>() < p.p_n;
                let s = if noised {
                    self.perturb_fk(&s, eps, p.noise, rng)
                } else {
                    s
                };
                (s, kind, centroid, hint, noised)
            }
            Order::Reference => {
                let (f, s) = rsi(&mut *rng)?;
                let noised = rng.random::<f64>() < p.p_n;
                if noised {
                    let (s, kind, centroid, hint) =
                        rsi_start(f, self.perturb_fk(&s, eps, p.noise, rng));
                    (s, kind, centroid, hint, true)
                } else if rng.random::<f64>() < p.p_e && !edges.is_empty() {
                    let here: Vec<&Edge> = edges
                        .iter()
                        .filter(|e| (e.dst_clip as usize, e.dst_frame as usize) == (clip, f))
                        .collect();
                    let e = if here.is_empty() {
                        &edges[rng.random_range(0..edges.len())]
                    } else {
                        here[rng.random_range(0..here.len())]
                    };
                    match e.aligned_start(lib) {
                        Some(st) => {
                            let src = (e.src_clip as usize, e.src_frame as usize);
                            (
                                st,
                                StartKind::Stg,
                                src,
                                (e.dst_clip as usize, e.dst_frame as usize),
                                false,
                            )
                        }
                        None => {
                            let (s, kind, centroid, hint) = rsi_start(f, s);
                            (s, kind, centroid, hint, false)
                        }
                    }
                } else {
                    let (s, kind, centroid, hint) = rsi_start(f, s);
                    (s, kind, centroid, hint, false)
                }
            }
        };
        let search: Vec<usize> = match p.search {
            Search::Skill => self.skill_clips.get(skill).cloned().unwrap_or_default(),
            Search::Clip => vec![hint.0],
        };
        let best = self.connect(&start, &search, (!noised).then_some(hint));
        let connection = best
            .and_then(|(beta, j)| Some((beta, j, n_masked(beta, p.tau, p.n_max, p.mask_rule)?)));
        let mut t = Trajectory {
            target_skill: skill.clone(),
            condition: class,
            start,
            start_kind: kind,
            noised,
            fallback: false,
            centroid: (centroid.0 as u32, centroid.1 as u32),
            connect: (0, 0),
            beta: 0.0,
            n_masked: 0,
            steps: Vec::new(),
            simulated: false,
        };
        let (beta, j, n) = match connection {
            Some(x) => x,
            None => {
                // No connection (β <= τ): a plain reference start instead.
                let f = match kind {
                    StartKind::Rsi => centroid.1,
                    StartKind::Stg => ats.sample_frame(clip, rng)?,
                };
                t.start = lib.state(clip, f)?;
                t.start_kind = StartKind::Rsi;
                t.noised = false;
                t.fallback = true;
                t.centroid = (clip as u32, f as u32);
                (1.0, (clip, f), 0)
            }
        };
        t.beta = beta;
        t.n_masked = n;
        t.connect = (j.0 as u32, j.1 as u32);
        t.steps = self.steps(j, n, p.connect, p.horizon);
        Some(t)
    }

    /// Eq. 6: the most similar candidate frame of `clips` to `start` (β and
    /// (clip, frame)); `prefer` is compared first and wins ties (so when it
    /// is the start itself, β = 1, the search stops there).
    pub fn connect(
        &self,
        start: &State,
        clips: &[usize],
        prefer: Option<(usize, usize)>,
    ) -> Option<(f64, (usize, usize))> {
        let sk = self.lib.skeleton;
        let none = Align {
            xy: false,
            yaw: false,
        };
        // S_k(s, s) = 1 exactly: a start that is a reference frame connects to it with β = 1.
        let sim = |s: &State| {
            if s == start {
                1.0
            } else {
                reward::similarity(s, start, sk, &self.weights, none)
            }
        };
        let mut best: Option<(f64, (usize, usize))> = None;
        if let Some((c, f)) = prefer.filter(|(c, _)| clips.contains(c)) {
            if let Some((_, s)) = self
                .cands
                .get(c)
                .and_then(|v| v.iter().find(|(g, _)| *g == f))
            {
                best = Some((sim(s), (c, f)));
            }
        }
        // S_k <= 1 (non-negative weights) and ties keep the first: nothing can beat 1.
        if best.is_some_and(|(b, _)| b >= 1.0) {
            return best;
        }
        for &c in clips {
            for (f, s) in self.cands.get(c).map_or(&[][..], Vec::as_slice) {
                if Some((c, *f)) == prefer {
                    continue;
                }
                let b = sim(s);
                if best.is_none_or(|(bb, _)| b > bb) {
                    best = Some((b, (c, *f)));
                }
            }
        }
        best
    }

    /// Steps that follow clip `clip` from `first` on with no masked state:
    /// the start, then `first`, `first + 1`, ... (at most `horizon` policy
    /// steps). The trainer uses it for a start that is a reference frame
    /// itself and for ε-NSI without the connection rule.
    pub fn follow(&self, clip: usize, first: usize, horizon: usize) -> Vec<Step> {
        self.steps((clip, first), 0, Connect::Paper, horizon)
    }

    /// The steps after connecting to `j` with `n` masked states.
    fn steps(&self, j: (usize, usize), n: u32, connect: Connect, horizon: usize) -> Vec<Step> {
        let mut v = vec![Step {
            masked: false,
            ref_clip: None,
            ref_frame: None,
        }];
        let (inserted, first) = match connect {
            Connect::Paper => (n, j.1),
            Connect::Reference if n == 0 => (0, j.1 + 1),
            Connect::Reference => (n - 1, j.1),
        };
        let inserted_step = Step {
            masked: true,
            ref_clip: None,
            ref_frame: None,
        };
        v.extend(std::iter::repeat_n(inserted_step, inserted as usize));
        let cf = &self.lib.frames[j.0];
        if let Some(last) = cf.last_valid() {
            for f in first..=last {
                if v.len() > horizon {
                    break;
                }
                v.push(Step {
                    masked: !cf.valid[f],
                    ref_clip: Some(j.0 as u32),
                    ref_frame: Some(f as u32),
                });
            }
        }
        v.truncate(horizon + 1);
        v
    }
}

/// The summary table: per target skill, trajectories per start kind, mean N
/// and mean length (policy steps).
pub fn summary(trajs: &[Trajectory], skills: &[String]) -> String {
    // one column per start label, at least 6 wide
    let width = |k: StartLabel| k.as_str().len().max(6);
    let mut s = format!("{:<14} {:>5} {:>6}", "target skill", "class", "trajs");
    for k in StartLabel::ALL {
        s += &format!(" {:>w$}", k.as_str(), w = width(k));
    }
    s += &format!(" {:>8} {:>6} {:>10}\n", "fallback", "mean N", "mean steps");
    let row = |name: &str, class: String, v: &[&Trajectory]| -> String {
        let n = v.len().max(1) as f64;
        let mean_n = v.iter().map(|t| t.n_masked as f64).sum::<f64>() / n;
        let mean_len = v.iter().map(|t| t.policy_steps() as f64).sum::<f64>() / n;
        let mut s = format!("{:<14} {:>5} {:>6}", name, class, v.len());
        for k in StartLabel::ALL {
            let count = v.iter().filter(|t| t.start_label() == k).count();
            s += &format!(" {:>w$}", count, w = width(k));
        }
        s + &format!(
            " {:>8} {:>6.2} {:>10.1}\n",
            v.iter().filter(|t| t.fallback).count(),
            mean_n,
            mean_len
        )
    };
    for sk in skills {
        let v: Vec<&Trajectory> = trajs.iter().filter(|t| &t.target_skill == sk).collect();
        if let Some(t) = v.first() {
            s += &row(sk, t.condition.to_string(), &v);
        }
    }
    s += &row("all", String::new(), &trajs.iter().collect::<Vec<_>>());
    s
}

#[cfg(test)]
mod tests {
    use super::super::ats::{Ats, AtsParams};
    use super::*;
    use crate::motion::library::ClipRow;
    use crate::motion::{ClipFrames, Skeleton};
    use crate::reward::DatasetKind;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// A small library: skill "a" (class 0, two clips of 30 frames; clip 1
    /// has frames 10-12 missing) and skill "b" (class 5, one clip of 25).
    fn lib() -> MotionLib {
        let sk = Skeleton::MocapHumanoid;
        let (j, b) = (sk.n_joints(), sk.n_bodies());
        let clip = |f: usize, x0: f32, phase: f32, missing: &[usize]| -> ClipFrames {
            let mut c = ClipFrames {
                frames: f,
                n_joints: j,
                n_bodies: b,
                n_objects: 1,
                ..Default::default()
            };
            for i in 0..f {
                let ok = !missing.contains(&i);
                let t = i as f32 * 0.05 + phase;
                let z = if ok { 1.0 } else { 0.0 };
                let yaw = 0.3 * t;
                let q = quat::from_expmap([0.0, 0.0, yaw as f64]).map(|v| v as f32);
                c.valid.push(ok);
                c.contact.push(false);
                c.root_pos
                    .extend([z * (x0 + t), z * 0.2 * t.sin(), z * 0.9]);
                c.root_rot.extend(if ok { q } else { [0.0; 4] });
                c.root_rot_expmap.extend([0.0, 0.0, z * yaw]);
                c.root_linvel.extend([z, 0.0, 0.0]);
                c.root_angvel.extend([0.0, 0.0, z * 0.3]);
                c.joint_rot
                    .extend((0..3 * j).map(|k| z * 0.4 * (t + k as f32 * 0.1).sin()));
                c.joint_vel
                    .extend((0..3 * j).map(|k| z * (t + k as f32).cos()));
                c.body_pos.extend((0..3 * b).map(|k| {
                    let r = [x0 + t, 0.2 * t.sin(), 0.9];
                    z * (r[k % 3] + 0.3 * ((k / 3) as f32 * 0.7 + t).sin())
                }));
                c.body_vel.extend((0..3 * b).map(|_| z * 0.5));
                c.obj_pos.extend([
                    z * (x0 + t + 0.3),
                    z * 0.1,
                    z * (0.5 + 0.3 * (4.0 * t).sin()),
                ]);
                c.obj_rot.extend([0.0, 0.0, 0.0, z]);
                c.obj_rot_expmap.extend([0.0; 3]);
                c.obj_linvel.extend([z, 0.0, 0.0]);
                c.obj_angvel.extend([0.0; 3]);
            }
            c
        };
        let row = |id: u32, skill: &str, class: u16, f: u32| ClipRow {
            clip_id: id,
            name: format!("{skill}{id}"),
            dataset: "synthetic".into(),
            skill: skill.into(),
            class,
            label: skill.into(),
            source: String::new(),
            sha256: String::new(),
            frames: f,
            valid_frames: f,
            fps: 60.0,
            layout: "D337".into(),
            skeleton: sk.name().into(),
            objects: vec!["ball".into()],
        };
        MotionLib {
            skeleton: sk,
            clips: vec![row(0, "a", 0, 30), row(1, "a", 0, 30), row(2, "b", 5, 25)],
            frames: vec![
                clip(30, 0.0, 0.0, &[]),
                clip(30, 5.0, 0.7, &[10, 11, 12]),
                clip(25, 0.5, 0.2, &[]),
            ],
        }
    }

    fn weights() -> Weights {
        Weights::sm(DatasetKind::BallPlay)
    }

    fn edge(lib: &MotionLib) -> Edge {
        let (src, dst) = (lib.state(2, 7).unwrap(), lib.state(0, 9).unwrap());
        let w = weights();
        let beta = reward::similarity(
            &dst,
            &src,
            lib.skeleton,
            &w,
            Align {
                xy: false,
                yaw: false,
            },
        );
        Edge {
            target_skill: "a".into(),
            target_class: 0,
            src_skill: "b".into(),
            src_clip: 2,
            src_frame: 7,
            dst_clip: 0,
            dst_frame: 9,
            beta,
            n_masked: n_masked(beta, 1e-10, 10, MaskRule::Paper).unwrap(),
            align_yaw: 0.0,
            align_dx: 0.0,
            align_dy: 0.0,
        }
    }

    #[test]
    fn without_switch_and_noise_every_start_is_its_own_reference_frame() {
        let lib = lib();
        let s = StfSampler::new(&lib, &[edge(&lib)], weights());
        let ats = Ats::new(&lib).weights(&AtsParams::default());
        let p = StfParams {
            p_e: 0.0,
            p_n: 0.0,
            ..StfParams::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..200 {
            let t = s.sample(&ats, &p, &mut rng).unwrap();
            assert_eq!(
                (t.start_kind, t.noised, t.fallback),
                (StartKind::Rsi, false, false)
            );
            assert_eq!(t.beta, 1.0);
            assert_eq!(t.n_masked, 0);
            assert_eq!(t.connect, t.centroid);
            let (c, f) = (t.centroid.0 as usize, t.centroid.1 as usize);
            assert_eq!(t.start, lib.state(c, f).unwrap());
            assert!(ats.frames[c][f] > 0.0);
            // Eq. 7: start, then ŝ_k, ŝ_{k+1}, ... to the clip end or the horizon
            assert_eq!(
                t.steps[0],
                Step {
                    masked: false,
                    ref_clip: None,
                    ref_frame: None
                }
            );
            for (i, st) in t.steps.iter().enumerate().skip(1) {
                assert_eq!(st.ref_clip, Some(c as u32));
                assert_eq!(st.ref_frame, Some((f + i - 1) as u32));
                assert_eq!(st.masked, !lib.frames[c].valid[f + i - 1]);
            }
            assert_eq!(t.policy_steps(), (lib.frames[c].frames - f).min(60));
        }
    }

    #[test]
    fn perturbation_stays_in_the_box_keeps_quaternions_unit_and_moves_bodies_rigidly() {
        let lib = lib();
        let s0 = lib.state(0, 5).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        // zero radii: the state itself
        assert_eq!(perturb(&s0, &Eps::all(0.0), Noise::Uniform, &mut rng), s0);
        for noise in [Noise::Uniform, Noise::Gaussian] {
            for _ in 0..50 {
                let e = Eps::all(0.1);
                let s = perturb(&s0, &e, noise, &mut rng);
                let n: f32 = s.root_rot.iter().map(|v| v * v).sum();
                assert!((n - 1.0).abs() < 1e-5);
                // the exp-map is the same rotation as the quaternion
                let q = quat::from_expmap(s.root_rot_expmap.map(|v| v as f64));
                assert!(quat::dot(q, s.root_rot.map(|v| v as f64)).abs() > 1.0 - 1e-6);
                // bodies keep their distances to the root
                for (a, b) in s.body_pos.chunks_exact(3).zip(s0.body_pos.chunks_exact(3)) {
                    let d = |p: &[f32], r: [f32; 3]| -> f32 {
                        (0..3).map(|i| (p[i] - r[i]).powi(2)).sum::<f32>().sqrt()
                    };
                    assert!((d(a, s.root_pos) - d(b, s0.root_pos)).abs() < 1e-5);
                }
                if noise == Noise::Uniform {
                    for i in 0..3 {
                        assert!((s.root_pos[i] - s0.root_pos[i]).abs() <= 0.1 + 1e-6);
                        assert!((s.obj_pos[i] - s0.obj_pos[i]).abs() <= 0.1 + 1e-6);
                    }
                    for (a, b) in s.joint_rot.iter().zip(&s0.joint_rot) {
                        assert!((a - b).abs() <= 0.1 + 1e-6);
                    }
                    // rotation angle of the root noise at most |(0.1, 0.1, 0.1)|
                    let d = quat::mul(
                        s.root_rot.map(|v| v as f64),
                        quat::conj(s0.root_rot.map(|v| v as f64)),
                    );
                    assert!(quat::norm(quat::to_expmap(d)) <= 0.1 * 3f64.sqrt() + 1e-5);
                }
            }
        }
    }

    #[test]
    fn steps_follow_eq7_or_the_reference_indexing() {
        let lib = lib();
        let s = StfSampler::new(&lib, &[], weights());
        let st = |v: &[Step]| -> Vec<(bool, Option<u32>)> {
            v.iter().map(|x| (x.masked, x.ref_frame)).collect()
        };
        let paper = s.steps((1, 7), 2, Connect::Paper, 8);
        assert_eq!(
            st(&paper),
            [
                (false, None),
                (true, None),
                (true, None),
                (false, Some(7)),
                (false, Some(8)),
                (false, Some(9)),
                (true, Some(10)),
                (true, Some(11)),
                (true, Some(12))
            ]
        );
        let r = s.steps((1, 7), 2, Connect::Reference, 3);
        assert_eq!(
            st(&r),
            [
                (false, None),
                (true, None),
                (false, Some(7)),
                (false, Some(8))
            ]
        );
        let r0 = s.steps((0, 27), 0, Connect::Reference, 60);
        assert_eq!(
            st(&r0),
            [(false, None), (false, Some(28)), (false, Some(29))]
        );
        assert_eq!(s.steps((0, 28), 10, Connect::Paper, 60).len(), 1 + 10 + 2);
    }

    #[test]
    fn switch_noise_orders_and_fallback() {
        let lib = lib();
        let e = edge(&lib);
        let s = StfSampler::new(&lib, std::slice::from_ref(&e), weights());
        let ats = Ats::new(&lib).weights(&AtsParams::default());
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        // p_e = 1: every start of skill a is the edge's aligned start
        let p = StfParams {
            p_e: 1.0,
            p_n: 0.0,
            ..StfParams::default()
        };
        for _ in 0..40 {
            let t = s.sample_in_clip(1, &ats, &p, &mut rng).unwrap();
            assert_eq!(t.start_kind, StartKind::Stg);
            assert_eq!(t.centroid, (2, 7));
            assert_eq!(t.start, e.aligned_start(&lib).unwrap());
            assert_eq!(t.condition, 0);
            let (beta, j) = s.connect(&t.start, &[0, 1], None).unwrap();
            assert_eq!((beta, (j.0 as u32, j.1 as u32)), (t.beta, t.connect));
            // skill b has no edges: always its own frames
            let t = s.sample_in_clip(2, &ats, &p, &mut rng).unwrap();
            assert_eq!((t.start_kind, t.condition), (StartKind::Rsi, 5));
        }
        // paper order with p_e = p_n = 1: switched and noised
        let both = StfParams {
            p_e: 1.0,
            p_n: 1.0,
            ..StfParams::default()
        };
        let t = s.sample_in_clip(0, &ats, &both, &mut rng).unwrap();
        assert_eq!(t.kind_label(), "stg+noise");
        // reference order: noise excludes the switch
        let refo = StfParams {
            order: Order::Reference,
            ..both.clone()
        };
        for _ in 0..20 {
            assert_eq!(
                s.sample_in_clip(0, &ats, &refo, &mut rng)
                    .unwrap()
                    .kind_label(),
                "rsi+noise"
            );
        }
        let refs = StfParams { p_n: 0.0, ..refo };
        assert_eq!(
            s.sample_in_clip(0, &ats, &refs, &mut rng)
                .unwrap()
                .kind_label(),
            "stg"
        );
        // tau = 1: nothing connects, every start falls back to a plain reference frame
        let strict = StfParams { tau: 1.0, ..both };
        for _ in 0..20 {
            let t = s.sample_in_clip(0, &ats, &strict, &mut rng).unwrap();
            assert!(t.fallback);
            assert_eq!((t.kind_label(), t.beta, t.n_masked), ("rsi", 1.0, 0));
            assert_eq!(t.start, lib.state(0, t.connect.1 as usize).unwrap());
            assert_eq!(t.connect, t.centroid);
        }
    }

    #[test]
    fn getup_radii_are_a_class_override() {
        let p = StfParams::default();
        assert_eq!(p.eps_for(0).root_pos, 1.0);
        assert_eq!(p.eps_for(0).root_vel, 1.0);
        assert_eq!(p.eps_for(0).dof, 0.1);
        assert_eq!(*p.eps_for(13), Eps::all(0.1));
    }

    #[test]
    fn start_labels_name_each_kind_and_noise() {
        let want = [
            (StartKind::Rsi, false, "rsi"),
            (StartKind::Rsi, true, "rsi+noise"),
            (StartKind::Stg, false, "stg"),
            (StartKind::Stg, true, "stg+noise"),
        ];
        for (l, (kind, noised, name)) in StartLabel::ALL.into_iter().zip(want) {
            assert_eq!((StartLabel::of(kind, noised), l.as_str()), (l, name));
        }
        assert_eq!(
            summary(&[], &[]).lines().next(),
            Some(
                "target skill   class  trajs    rsi rsi+noise    stg stg+noise fallback mean N mean steps"
            )
        );
    }
}
