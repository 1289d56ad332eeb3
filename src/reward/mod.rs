//! Rewards and state similarity (paper Appendix B.3-B.4; reference code:
//! Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/skillmimic1.py` and
//! `skillmimic1_unified.py` for the reward,
//! `skillmimic/utils/motion_data_handler.py` for the similarity).
//!
//! * SM multiplicative reward, Eqs. 12-17: r = r_b r_o r_rel r_cg, every term
//!   exp(-lambda * MSE); weights per dataset from Table 8 ([`Weights::sm`]).
//! * DM additive reward, Eq. 18: r = r_p + r_r + r_rv + r_op, Table 9
//!   ([`Weights::dm`]).
//! * Similarity S_k(s_A, s_B) = r_b r_o r_rel, Eq. 19, after aligning s_B's
//!   root xy (and, by default, its heading) to s_A's ([`similarity`]).
//!
//! What each MSE runs over (the paper names the terms; the reference code fixes
//! the operands, `skillmimic1.py`): positions = the root position followed by
//! the 17 key bodies (54 numbers); rotations = the root exp-map followed by
//! every joint exp-map, compared component by component (159 or 183 numbers);
//! body velocities = the same 18 points' velocities; joint velocities = the
//! joint exp-map velocities; object terms over every object's position,
//! quaternion, linear and angular velocity; relative motion = (key point -
//! object position) for the 18 points and every object.
//!
//! Contact graph (Eq. 17): the paper's three pairs ball-hands, ball-body and
//! body-hands, with the reference edges taken from the clip's single contact
//! flag (ball-hands = flag, the other two = 0). The reference code's two
//! node-level terms (any-body contact penalty, ball contact vs. flag) are the
//! option [`ContactRule::Reference`]. ParaHome and Locomotion have r_cg = 1.
//! The flag behaves as hand-ball proximity, so the simulation's ball-hands
//! edge is by default a proximity test ([`ContactDetect`]); the touching
//! pairs stay options.
//!
//! Root rotation: compared on the nearest exp-map branch by default
//! ([`RootRot::Nearest`]); the reference code's raw component difference is
//! [`RootRot::Raw`].
//! The reference code's extra smoothness factor (`skillmimic1.py`) is the
//! option [`RewardOptions::smoothness`], off by default.

use crate::motion::quat;
use crate::motion::{Skeleton, State};
use crate::sim::world::GRAVITY;
use serde::{Deserialize, Serialize};

/// Which table row of weights applies.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DatasetKind {
    /// BallPlay / BallPlay-M: object terms and contact graph on.
    BallPlay,
    /// Locomotion: body terms only.
    Locomotion,
    /// ParaHome: object terms on, contact graph off.
    ParaHome,
}

impl DatasetKind {
    /// The kind of an ingested library: the ParaHome skeleton is ParaHome;
    /// clips without any object (the Locomotion manifest drops its dummy
    /// ball) are Locomotion; the rest is BallPlay.
    pub fn of_library(lib: &crate::motion::MotionLib) -> DatasetKind {
        if lib.skeleton == Skeleton::ParaHome {
            DatasetKind::ParaHome
        } else if lib.frames.iter().all(|f| f.n_objects == 0) {
            DatasetKind::Locomotion
        } else {
            DatasetKind::BallPlay
        }
    }
}

/// Reward weights (the lambdas of Eqs. 13-18). A zero weight makes its SM
/// factor exp(0) = 1; [`dm_reward`] leaves zero-weight terms out of its sum.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Weights {
    /// Key-point position.
    pub p: f64,
    /// Root and joint rotation.
    pub r: f64,
    /// Key-point velocity.
    pub pv: f64,
    /// Joint velocity.
    pub rv: f64,
    /// Object position.
    pub op: f64,
    /// Object rotation.
    pub or: f64,
    /// Object linear velocity.
    pub opv: f64,
    /// Object angular velocity.
    pub orv: f64,
    /// Relative motion.
    pub rel: f64,
    /// Contact graph: ball-hands, ball-body, body-hands.
    pub cg: [f64; 3],
    /// Object mechanical energy per unit mass, (kg/J)^2 ([`Errors::oe`]):
    /// not a term of the paper (0 in every preset).
    #[serde(default)]
    pub oe: f64,
}

impl Weights {
    /// SM weights, paper Table 8.
    pub fn sm(kind: DatasetKind) -> Weights {
        let body = Weights {
            p: 20.0,
            r: 20.0,
            pv: 0.0,
            rv: 0.0,
            op: 0.0,
            or: 0.0,
            opv: 0.0,
            orv: 0.0,
            rel: 0.0,
            cg: [0.0; 3],
            oe: 0.0,
        };
        match kind {
            DatasetKind::BallPlay => Weights {
                op: 1.0,
                rel: 20.0,
                cg: [5.0; 3],
                ..body
            },
            DatasetKind::Locomotion => body,
            DatasetKind::ParaHome => Weights {
                op: 1.0,
                rel: 20.0,
                ..body
            },
        }
    }

    /// These weights without the object and contact terms: the reward of
    /// classes 0 and 10 (no object; the body factor only, as in
    /// Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/skillmimic1_unified.py`
    /// and `skillmimic/utils/motion_data_handler.py`).
    pub fn without_object(self) -> Weights {
        Weights {
            op: 0.0,
            or: 0.0,
            opv: 0.0,
            orv: 0.0,
            rel: 0.0,
            cg: [0.0; 3],
            oe: 0.0,
            ..self
        }
    }

    /// DM weights, paper Table 9 (ParaHome uses the BallPlay row, as the
    /// reference code's DM ParaHome configs do, Ingrid789/SkillMimic-V2
    /// `skillmimic/data/cfg/parahome_dm/*.yaml`).
    pub fn dm(kind: DatasetKind) -> Weights {
        Weights {
            p: 40.0,
            r: 2.0,
            pv: 0.0,
            rv: 0.1,
            op: if kind == DatasetKind::Locomotion {
                0.0
            } else {
                40.0
            },
            or: 0.0,
            opv: 0.0,
            orv: 0.0,
            rel: 0.0,
            cg: [0.0; 3],
            oe: 0.0,
        }
    }
}

/// Per-term replacements of the training reward's weights
/// (`train.reward_weights`, for example `{ opv = 0.5 }`): each given key
/// replaces that lambda of [`Weights::sm`] or [`Weights::dm`] for the
/// classes with an object (classes 0 and 10 keep their body-only weights,
/// [`Weights::without_object`]). The mean SM reward that training and
/// evaluation report is still scored with the paper's weights, so runs stay
/// comparable. Every key absent (the default) leaves the paper's weights.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WeightOverrides {
    /// Key-point position.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub p: Option<f64>,
    /// Root and joint rotation.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub r: Option<f64>,
    /// Key-point velocity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pv: Option<f64>,
    /// Joint velocity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rv: Option<f64>,
    /// Object position.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub op: Option<f64>,
    /// Object rotation.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub or: Option<f64>,
    /// Object linear velocity, (s/m)^2: lambda_opv of Eq. 14 (0 in the
    /// paper's Table 8 and in the reference code's `skillmimic.yaml`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub opv: Option<f64>,
    /// Object angular velocity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub orv: Option<f64>,
    /// Relative motion.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rel: Option<f64>,
    /// Contact graph: ball-hands, ball-body, body-hands.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cg: Option<[f64; 3]>,
    /// Object mechanical energy per unit mass, (kg/J)^2 ([`Errors::oe`]; not
    /// in the paper): scores a push by the bounce it buys, whatever the
    /// ball's phase.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub oe: Option<f64>,
}

impl WeightOverrides {
    /// No key given.
    pub fn is_empty(&self) -> bool {
        *self == WeightOverrides::default()
    }

    /// `w` with every given key replaced.
    pub fn apply(&self, w: Weights) -> Weights {
        Weights {
            p: self.p.unwrap_or(w.p),
            r: self.r.unwrap_or(w.r),
            pv: self.pv.unwrap_or(w.pv),
            rv: self.rv.unwrap_or(w.rv),
            op: self.op.unwrap_or(w.op),
            or: self.or.unwrap_or(w.or),
            opv: self.opv.unwrap_or(w.opv),
            orv: self.orv.unwrap_or(w.orv),
            rel: self.rel.unwrap_or(w.rel),
            cg: self.cg.unwrap_or(w.cg),
            oe: self.oe.unwrap_or(w.oe),
        }
    }

    /// Every given weight finite and >= 0.
    ///
    /// # Errors
    /// The first key that is not, named as `stage.reward_weights.KEY`.
    pub fn check(&self, stage: &str) -> anyhow::Result<()> {
        let cg = self.cg.unwrap_or_default();
        let keys = [
            ("p", self.p),
            ("r", self.r),
            ("pv", self.pv),
            ("rv", self.rv),
            ("op", self.op),
            ("or", self.or),
            ("opv", self.opv),
            ("orv", self.orv),
            ("rel", self.rel),
            ("oe", self.oe),
            ("cg[0]", Some(cg[0])),
            ("cg[1]", Some(cg[1])),
            ("cg[2]", Some(cg[2])),
        ];
        for (k, v) in keys {
            if let Some(v) = v {
                if !(v.is_finite() && v >= 0.0) {
                    anyhow::bail!("{stage}.reward_weights.{k} = {v}: needs a finite value >= 0");
                }
            }
        }
        Ok(())
    }
}

/// How the contact-graph term is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ContactRule {
    /// Paper Eq. 17: three pairs (ball-hands, ball-body, body-hands).
    #[default]
    Paper,
    /// Reference code (Ingrid789/SkillMimic-V2
    /// `skillmimic/env/tasks/skillmimic1.py`): body-contact penalty (weight
    /// cg\[2\]) and ball contact vs. the flag (weight cg\[0\]).
    Reference,
}

/// Contacts measured in the simulation (or given for a reference frame).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Contacts {
    /// Ball (object) touches a hand.
    pub ball_hands: bool,
    /// Ball touches the rest of the body.
    pub ball_body: bool,
    /// Hands touch the rest of the body.
    pub body_hands: bool,
    /// Any of the reference code's 17 penalty bodies has a contact (ground included).
    pub penalty_bodies: bool,
}

impl Contacts {
    /// The contact edges implied by a reference frame's single flag.
    pub fn of_reference(s: &State) -> Contacts {
        Contacts {
            ball_hands: s.contact,
            ..Contacts::default()
        }
    }
}

/// How the simulation decides that the ball touches a hand (the ball-hands
/// edge of the contact graph, compared with the clip's contact flag).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ContactDetect {
    /// A hand body's origin (wrist or finger joint) within
    /// [`RewardOptions::contact_radius`] of the ball's centre at any physics
    /// substep of the policy step: what the data's flag measures
    /// (`skillaug check-contact`, docs/training.md).
    #[default]
    Proximity,
    /// Touching collider pairs (pairs that push), at any physics substep of
    /// the policy step.
    Touch,
    /// Touching collider pairs after the last substep only (the reference
    /// code reads the post-step net contact forces,
    /// Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/skillmimic1.py`).
    TouchLast,
}

/// How the rotation term compares the root exp-maps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RootRot {
    /// The simulated root exp-map on the branch (angle + 2 pi k) nearest to
    /// the reference's, so one rotation stored two ways costs nothing.
    #[default]
    Nearest,
    /// Component differences of the raw exp-maps (Ingrid789/SkillMimic-V2
    /// `skillmimic/env/tasks/skillmimic1.py`: no
    /// angle wrapping).
    Raw,
}

/// Options of the SM reward.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RewardOptions {
    /// Contact-graph rule.
    pub contacts: ContactRule,
    /// How the ball-hands contact is detected in the simulation.
    pub contact_detect: ContactDetect,
    /// Radius of [`ContactDetect::Proximity`], m.
    pub contact_radius: f64,
    /// How the root rotations are compared.
    pub root_rot: RootRot,
    /// Multiply by the reference code's smoothness factor (needs the previous
    /// simulated joint velocities).
    pub smoothness: bool,
    /// Replacements of the training reward's weights (none by default).
    pub weights: WeightOverrides,
}

impl Default for RewardOptions {
    fn default() -> Self {
        RewardOptions {
            contacts: ContactRule::Paper,
            contact_detect: ContactDetect::Proximity,
            contact_radius: 0.2,
            root_rot: RootRot::Nearest,
            smoothness: false,
            weights: WeightOverrides::default(),
        }
    }
}

/// Each factor of the SM reward and their product.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SmTerms {
    /// r_p r_r r_pv r_rv (and the smoothness factor when enabled).
    pub body: f64,
    /// r_op r_or r_opv r_orv (and the energy factor, [`Errors::oe`], when
    /// weighted).
    pub object: f64,
    /// r_rel.
    pub rel: f64,
    /// r_cg.
    pub cg: f64,
    /// The reward: body * object * rel * cg.
    pub total: f64,
}

/// Mean of squared differences; 0 for empty inputs.
fn mse(a: impl IntoIterator<Item = f64>, b: impl IntoIterator<Item = f64>) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for (x, y) in a.into_iter().zip(b) {
        s += (x - y) * (x - y);
        n += 1;
    }
    if n == 0 {
        0.0
    } else {
        s / n as f64
    }
}

fn f(v: &[f32]) -> impl Iterator<Item = f64> + '_ {
    v.iter().map(|x| *x as f64)
}

/// Root position followed by the 17 key-body positions (54 numbers).
pub fn key_points(s: &State, sk: Skeleton) -> Vec<f64> {
    let mut v: Vec<f64> = f(&s.root_pos).collect();
    for b in sk.key_bodies() {
        v.extend(f(&s.body_pos[3 * b..3 * b + 3]));
    }
    v
}

/// Root linear velocity followed by the 17 key-body velocities.
fn key_velocities(s: &State, sk: Skeleton) -> Vec<f64> {
    let mut v: Vec<f64> = f(&s.root_linvel).collect();
    for b in sk.key_bodies() {
        v.extend(f(&s.body_vel[3 * b..3 * b + 3]));
    }
    v
}

/// Key points relative to each object: (k_i - o) for every object o.
fn relative(s: &State, sk: Skeleton) -> Vec<f64> {
    let kp = key_points(s, sk);
    let mut v = Vec::with_capacity(kp.len() * s.obj_pos.len() / 3);
    for o in s.obj_pos.chunks_exact(3) {
        for k in kp.chunks_exact(3) {
            v.extend((0..3).map(|c| k[c] - o[c] as f64));
        }
    }
    v
}

fn rotations(s: &State) -> impl Iterator<Item = f64> + '_ {
    f(&s.root_rot_expmap).chain(f(&s.joint_rot))
}

/// Object quaternions with each sign chosen to agree with `like` (q and -q
/// are the same rotation).
fn obj_quats_like(s: &State, like: &State) -> Vec<f64> {
    let mut v = Vec::with_capacity(s.obj_rot.len());
    for (q, r) in s.obj_rot.chunks_exact(4).zip(like.obj_rot.chunks_exact(4)) {
        let q = quat::sign_like([q[0], q[1], q[2], q[3]], [r[0], r[1], r[2], r[3]]);
        v.extend(q.map(|x| x as f64));
    }
    v
}

/// The per-term errors (MSEs) between a simulated and a reference state.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Errors {
    /// Key-point positions.
    pub p: f64,
    /// Root and joint rotations.
    pub r: f64,
    /// Key-point velocities.
    pub pv: f64,
    /// Joint velocities.
    pub rv: f64,
    /// Object positions.
    pub op: f64,
    /// Object quaternions.
    pub or: f64,
    /// Object linear velocities.
    pub opv: f64,
    /// Object angular velocities.
    pub orv: f64,
    /// Relative motion.
    pub rel: f64,
    /// Object mechanical energy per unit mass, (J/kg)^2: the mean over
    /// objects of (E_sim - E_ref)^2 with E = g z + |v|^2 / 2 (z the
    /// centre's height, m; v its velocity, m/s; g the simulation's
    /// [`GRAVITY`]). Nothing in the paper: a ball in free flight keeps its
    /// E, so after a push the error says how much bounce the push bought,
    /// whether or not the ball is where the clip has it at that step. The
    /// clip's E is only nearly constant in flight, since its stored
    /// velocity is a backward difference of positions (`obj_linvel`,
    /// `src/motion/clip.rs`).
    pub oe: f64,
}

/// Mechanical energy per unit mass of each object, J/kg: g z + |v|^2 / 2
/// from `obj_pos` and `obj_linvel` (3 values per object).
fn object_energies(s: &State) -> impl Iterator<Item = f64> + '_ {
    s.obj_pos
        .chunks_exact(3)
        .zip(s.obj_linvel.chunks_exact(3))
        .map(|(p, v)| {
            let v2: f64 = v.iter().map(|x| (*x as f64).powi(2)).sum();
            GRAVITY * p[2] as f64 + 0.5 * v2
        })
}

/// Default of the scale k of [`energy_bonus`], (kg/J)^2: a ball whose
/// energy per unit mass is 5 J/kg short of the reference's (about half a
/// metre of bounce) earns exp(-0.5) of the bonus.
pub const ENERGY_BONUS_SCALE: f64 = 0.02;

/// The additive ball-energy bonus of `train.energy_bonus`, added to the
/// training reward (the SM or DM reward) at every step of a class with an
/// object: `weight * exp(-scale * e.oe)`, with `e.oe` the squared error of
/// the ball's mechanical energy per unit mass against the reference's
/// ([`Errors::oe`], (J/kg)^2; `scale` in (kg/J)^2). In [0, weight].
///
/// Not in the paper or the reference code. Unlike the multiplicative `oe`
/// weight of the object factor (Eq. 14), which a step with a poorly tracked
/// body scores near 0 whatever the ball does, the bonus pays for the bounce
/// a push bought from the step of the release on, whatever the body's
/// factors: a task reward beside the imitation reward, as AMP (Peng et al.
/// 2021) adds its task reward to its style reward.
pub fn energy_bonus(e: &Errors, weight: f64, scale: f64) -> f64 {
    weight * (-scale * e.oe).exp()
}

/// Errors of `sim` against `reference`, raw root exp-maps.
pub fn errors(sim: &State, reference: &State, sk: Skeleton) -> Errors {
    errors_with(sim, reference, sk, RootRot::Raw)
}

/// Errors of `sim` against `reference` with the root rotation compared by
/// `root`.
pub fn errors_with(sim: &State, reference: &State, sk: Skeleton, root: RootRot) -> Errors {
    let r = match root {
        RootRot::Raw => mse(rotations(sim), rotations(reference)),
        RootRot::Nearest => {
            let e = quat::nearest_expmap(
                sim.root_rot_expmap.map(|v| v as f64),
                reference.root_rot_expmap,
            );
            mse(e.into_iter().chain(f(&sim.joint_rot)), rotations(reference))
        }
    };
    Errors {
        p: mse(key_points(sim, sk), key_points(reference, sk)),
        r,
        pv: mse(key_velocities(sim, sk), key_velocities(reference, sk)),
        rv: mse(f(&sim.joint_vel), f(&reference.joint_vel)),
        op: mse(f(&sim.obj_pos), f(&reference.obj_pos)),
        or: mse(obj_quats_like(sim, reference), f(&reference.obj_rot)),
        opv: mse(f(&sim.obj_linvel), f(&reference.obj_linvel)),
        orv: mse(f(&sim.obj_angvel), f(&reference.obj_angvel)),
        rel: mse(relative(sim, sk), relative(reference, sk)),
        oe: mse(object_energies(sim), object_energies(reference)),
    }
}

fn body_factor(e: &Errors, w: &Weights) -> f64 {
    (-w.p * e.p - w.r * e.r - w.pv * e.pv - w.rv * e.rv).exp()
}

fn object_factor(e: &Errors, w: &Weights) -> f64 {
    (-w.op * e.op - w.or * e.or - w.opv * e.opv - w.orv * e.orv - w.oe * e.oe).exp()
}

/// The reference code's hidden smoothness factor (Ingrid789/SkillMimic-V2
/// `skillmimic/env/tasks/skillmimic1.py`):
/// exp(-0.1 mean((qd - qd_prev)^2 / (1e12 (qd_ref^2 + 1e-12)))).
pub fn smoothness(joint_vel: &[f32], prev_joint_vel: &[f32], ref_joint_vel: &[f32]) -> f64 {
    let n = joint_vel.len().max(1) as f64;
    let s: f64 = joint_vel
        .iter()
        .zip(prev_joint_vel)
        .zip(ref_joint_vel)
        .map(|((v, p), r)| {
            let d = (*v - *p) as f64;
            d * d / (1e12 * ((*r as f64).powi(2) + 1e-12))
        })
        .sum();
    (-0.1 * s / n).exp()
}

/// SM reward of `sim` against `reference` (Eqs. 12-17). `prev_joint_vel` is
/// used only with the smoothness option.
pub fn sm_reward(
    sim: &State,
    reference: &State,
    sim_contacts: &Contacts,
    sk: Skeleton,
    w: &Weights,
    opts: &RewardOptions,
    prev_joint_vel: Option<&[f32]>,
) -> SmTerms {
    let e = errors_with(sim, reference, sk, opts.root_rot);
    let smooth = smoothness_factor(sim, reference, opts, prev_joint_vel);
    sm_terms(&e, smooth, reference, sim_contacts, w, opts)
}

/// The reference code's smoothness factor of `sim` against `reference`
/// when `opts` asks for it and the previous joint velocities are known
/// ([`smoothness`]), else `None`.
pub fn smoothness_factor(
    sim: &State,
    reference: &State,
    opts: &RewardOptions,
    prev_joint_vel: Option<&[f32]>,
) -> Option<f64> {
    prev_joint_vel
        .filter(|_| opts.smoothness)
        .map(|prev| smoothness(&sim.joint_vel, prev, &reference.joint_vel))
}

/// The SM factors and their product (Eqs. 12-17) from errors `e` already
/// measured against `reference` ([`errors_with`]) and the smoothness factor
/// `smooth` ([`smoothness_factor`]), under weights `w`: [`sm_reward`] without
/// measuring the errors again, so that one step can be scored under two
/// sets of weights.
pub fn sm_terms(
    e: &Errors,
    smooth: Option<f64>,
    reference: &State,
    sim_contacts: &Contacts,
    w: &Weights,
    opts: &RewardOptions,
) -> SmTerms {
    let mut body = body_factor(e, w);
    if let Some(f) = smooth {
        body *= f;
    }
    let object = object_factor(e, w);
    let rel = (-w.rel * e.rel).exp();
    let r = Contacts::of_reference(reference);
    let b = |x: bool| -> f64 {
        if x {
            1.0
        } else {
            0.0
        }
    };
    let cg_err = match opts.contacts {
        ContactRule::Paper => {
            w.cg[0] * (b(sim_contacts.ball_hands) - b(r.ball_hands)).abs()
                + w.cg[1] * (b(sim_contacts.ball_body) - b(r.ball_body)).abs()
                + w.cg[2] * (b(sim_contacts.body_hands) - b(r.body_hands)).abs()
        }
        ContactRule::Reference => {
            let ball = sim_contacts.ball_hands || sim_contacts.ball_body;
            w.cg[2] * b(sim_contacts.penalty_bodies)
                + w.cg[0] * (b(ball) - b(reference.contact)).abs()
        }
    };
    let cg = (-cg_err).exp();
    SmTerms {
        body,
        object,
        rel,
        cg,
        total: body * object * rel * cg,
    }
}

/// The SM reward with a floor `floor` = ε in [0, 1] under the product of
/// the ball's factors: r_b (ε + (1 - ε) r_o r_rel r_cg), so a step whose
/// ball is lost still earns ε of the body's factor, where Eq. 12's product
/// (ε = 0, `t.total` itself) gives it almost nothing; ε = 1 is r_b alone.
/// Not in the paper or the reference code (`train.object_floor`,
/// docs/training.md).
pub fn floored_total(t: &SmTerms, floor: f64) -> f64 {
    if floor == 0.0 {
        return t.total;
    }
    t.body * (floor + (1.0 - floor) * (t.object * t.rel * t.cg))
}

/// DM additive reward (Eq. 18): r_p + r_r + r_rv + r_op, each exp(-lambda
/// MSE); a term whose weight is zero is left out (Locomotion has no r_op), so
/// the range is [0, number of weighted terms]. `root` compares the root
/// rotations as in [`sm_reward`].
pub fn dm_reward(sim: &State, reference: &State, sk: Skeleton, w: &Weights, root: RootRot) -> f64 {
    let e = errors_with(sim, reference, sk, root);
    [(w.p, e.p), (w.r, e.r), (w.rv, e.rv), (w.op, e.op)]
        .iter()
        .filter(|(wt, _)| *wt > 0.0)
        .map(|(wt, err)| (-wt * err).exp())
        .sum()
}

/// How a state is moved onto another before comparing (Ingrid789/SkillMimic-V2
/// `skillmimic/utils/motion_data_handler.py`, `get_local_motion`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Align {
    /// Move the root's x, y onto the target's (paper B.4).
    pub xy: bool,
    /// Also turn about z so the headings agree (reference code; on by default).
    pub yaw: bool,
}

impl Default for Align {
    fn default() -> Self {
        Align {
            xy: true,
            yaw: true,
        }
    }
}

/// The horizontal move that [`align_to`] applies: (yaw angle about z, rad;
/// the pivot = `s`'s root xy; the new root xy).
pub fn alignment(target: &State, s: &State, a: Align) -> (f64, [f64; 2], [f64; 2]) {
    let yaw = if a.yaw {
        quat::wrap_angle(quat::heading(target.root_rot) - quat::heading(s.root_rot))
    } else {
        0.0
    };
    let pivot = [s.root_pos[0] as f64, s.root_pos[1] as f64];
    let to = if a.xy {
        [target.root_pos[0] as f64, target.root_pos[1] as f64]
    } else {
        pivot
    };
    (yaw, pivot, to)
}

/// `s` moved rigidly about the vertical so that its root's x, y (and heading)
/// match `target`'s; heights and joint rotations are unchanged. Root and
/// object angular velocities are left as they are (the ingested root rate is
/// a body-frame rate, invariant under the turn).
pub fn align_to(target: &State, s: &State, a: Align) -> State {
    let (yaw, pivot, to) = alignment(target, s, a);
    apply_alignment(s, yaw, pivot, to)
}

/// Apply a turn of `yaw` about the vertical through `pivot`, then move the
/// pivot to `to`.
pub fn apply_alignment(s: &State, yaw: f64, pivot: [f64; 2], to: [f64; 2]) -> State {
    let (sn, cs) = yaw.sin_cos();
    let rot = |x: f64, y: f64| (cs * x - sn * y, sn * x + cs * y);
    let point = |p: &mut [f32]| {
        let (x, y) = rot(p[0] as f64 - pivot[0], p[1] as f64 - pivot[1]);
        p[0] = (x + to[0]) as f32;
        p[1] = (y + to[1]) as f32;
    };
    let vector = |v: &mut [f32]| {
        let (x, y) = rot(v[0] as f64, v[1] as f64);
        v[0] = x as f32;
        v[1] = y as f32;
    };
    let qz = quat::from_expmap([0.0, 0.0, yaw]);
    let turn = |q: &mut [f32]| {
        let r = quat::mul(qz, [q[0] as f64, q[1] as f64, q[2] as f64, q[3] as f64]);
        for c in 0..4 {
            q[c] = r[c] as f32;
        }
    };
    let mut o = s.clone();
    point(&mut o.root_pos);
    vector(&mut o.root_linvel);
    if yaw != 0.0 {
        turn(&mut o.root_rot);
        let q = o.root_rot.map(|v| v as f64);
        o.root_rot_expmap = quat::to_expmap(q).map(|v| v as f32);
        o.obj_rot.chunks_exact_mut(4).for_each(turn);
    }
    o.body_pos.chunks_exact_mut(3).for_each(point);
    o.body_vel.chunks_exact_mut(3).for_each(vector);
    o.obj_pos.chunks_exact_mut(3).for_each(point);
    o.obj_linvel.chunks_exact_mut(3).for_each(vector);
    o
}

/// Kinematic similarity S_k(s_A, s_B) = r_b r_o r_rel (Eq. 19) with `b`
/// aligned onto `a` first; contacts are not compared.
pub fn similarity(a: &State, b: &State, sk: Skeleton, w: &Weights, align: Align) -> f64 {
    // The STF connection (Eq. 6) compares without alignment once per candidate
    // frame: skip the copy of the whole state there.
    let b = if align.xy || align.yaw {
        std::borrow::Cow::Owned(align_to(a, b, align))
    } else {
        std::borrow::Cow::Borrowed(b)
    };
    let e = errors(&b, a, sk);
    body_factor(&e, w) * object_factor(&e, w) * (-w.rel * e.rel).exp()
}

#[cfg(test)]
pub(crate) mod tests;
