//! One simulated world: the MJCF humanoid, a ground plane and the task's
//! objects, in rapier3d 0.36 (the model, gains and settings of SkillMimic-V2;
//! sources and measured facts in docs/simulation.md).
//!
//! **Model.** Every body of the MJCF becomes a dynamic rigid body whose frame
//! is the MJCF body frame; its geoms (capsules from `fromto`, spheres, boxes)
//! (and a cylinder from `fromto` in the ParaHome head) are its colliders, with the geom density (`density=""` and absent: 1000,
//! MuJoCo's default; a negative box half-extent is taken as its absolute
//! value). Each body's three hinges become one spherical *impulse* joint to
//! its parent (impulse joints measured about 35x faster than multibody
//! joints at this size, docs/simulation.md), anchored at the child's origin with identity joint
//! frames, so the joint's relative rotation is the body's local rotation and
//! its coordinates are the exp-map triples of the data (docs/simulation.md).
//!
//! **Departures from the MJCF**, needed for impulse joints to be stable with
//! the model's extreme mass ratios (docs/simulation.md; fields of
//! [`SimOptions`], whose defaults for the clips' frame rate,
//! [`SimOptions::for_fps`], every training and evaluation uses, and which
//! only `skillaug bench sim --set sim.KEY=VALUE` varies):
//! the MJCF joint armature (0.02) is added as principal inertia of every
//! non-root body, non-hand bodies weigh at least `min_mass` (0.5 kg: this
//! changes only the 5.6 g Chest sphere and the toes), and hand bodies at
//! least `hand_min_mass` (0.05 kg: every finger segment, 1.5-22 g in the
//! model).
//!
//! **PD drives** (target = pi * action, docs/simulation.md): implicit, solved by the engine
//! (`MotorModel::ForceBased` with the MJCF stiffness/damping as kp/kd,
//! torque = kp (target - q) - kd dq/dt per axis, no force limit; with
//! [`World::apply_action_with_rates`] kp (target - q) + kd (rate - dq/dt)). A target
//! triple `e` (target = pi * action) is converted to the three angles a
//! spherical joint's motors measure, `2 asin(exp(e).imag[i])`.
//! The joint rows are solved one at a time (scalar, about a quarter of the
//! step): rapier 0.36 batches joints into SIMD lanes only within a graph
//! colour of at least 64 joints, and one humanoid has 52 joints in all. A
//! drive that rapier could batch (the target rotation as a soft locked-axis
//! constraint) was measured no faster for that reason (3,757 against 3,775
//! steps/s) and is not offered.
//!
//! **Collisions.** Self-collision is on except between a body and its
//! parent (`contacts_enabled(false)` on the joint); objects collide with
//! everything; the ground is the static half-space z <= 0
//! (restitution 0.8, friction 1.0, docs/simulation.md). Gravity is -z (the
//! BallPlay model is built y-up; the data's root rotation carries it into
//! the z-up world).
//!
//! **State.** [`World::set_state`] / [`World::get_state`] use the layout of
//! the ingested frames ([`State`]): root pose and velocity, joint exp-maps
//! and their rates, body positions and velocities (of the body frame
//! origins), object poses and velocities. Setting places every body by
//! forward kinematics of the joint triples (the stored capture positions
//! are not used: the model's limb lengths differ) and derives body
//! velocities from the root and joint rates through the exp-map Jacobian
//! ([`super::rot`]). Root and object angular velocities are read and written
//! in the frame the tables use (`angvel_frame`, body frame by default: the
//! reference loader's rule, docs/simulation.md).

use super::mjcf::Model;
use super::objects::ObjectSpec;
use super::rot;
use crate::motion::clip::AngvelFrame;
use crate::motion::state::State;
use crate::reward::{ContactDetect, Contacts};
use anyhow::{bail, Result};
use rapier3d::math::{Pose, Rotation, Vector};
use rapier3d::prelude::*;
use serde::{Deserialize, Serialize};

/// Physics settings: [`SimOptions::for_fps`] in training and evaluation;
/// `skillaug bench sim --set sim.KEY=VALUE` tries others.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimOptions {
    /// Physics rate, Hz (120 BallPlay/Locomotion, 60 ParaHome).
    pub physics_hz: f64,
    /// Physics steps per policy step (2: a 60 Hz policy; 30 Hz for ParaHome).
    pub substeps: usize,
    /// rapier solver iterations (its internal substeps) per physics step.
    pub solver_iterations: usize,
    /// rapier internal PGS iterations.
    pub pgs_iterations: usize,
    /// rapier internal stabilisation (position correction) iterations.
    pub stabilization_iterations: usize,
    /// rapier's contact recycling (reuse a touching pair's contact points
    /// and normal while its relative pose drifted less than 5 cm; rapier's
    /// default). Off, every pair is recomputed at every physics step; the
    /// humanoid steps about as fast either way (docs/simulation.md).
    pub contact_recycling: bool,
    /// Add the MJCF joint armature as principal inertia of non-root bodies.
    pub armature_inertia: bool,
    /// Minimum mass of non-hand bodies, kg (0 disables).
    pub min_mass: f32,
    /// Minimum mass of hand (wrist and finger) bodies, kg (0 disables; see
    /// the module doc).
    pub hand_min_mass: f32,
    /// Collisions between non-adjacent bodies of the humanoid.
    pub self_collision: bool,
    /// Collisions among the bodies of one hand (its wrist and fingers).
    pub hand_self_collision: bool,
    /// Friction of the humanoid and the ground.
    pub friction: f32,
    /// Ground restitution.
    pub ground_restitution: f32,
    /// Natural frequency of contacts with the ground, Hz (rapier's default
    /// 60). Under random actions a toe motor can press its 0.5 kg toe into
    /// the ground with 2-3 kN: at 120 Hz it sank 3.5 cm (5 of 6 seeds and
    /// starts had steps below 2 cm); at 360 Hz none of 460,800 world-steps
    /// over 12 seeds and starts went below 1.5 cm. 600 Hz goes with the
    /// smaller `prediction_distance` below: every body stayed above
    /// -1.6 cm (toes the deepest, a fingertip next) over 3 seeds of 64
    /// worlds x 10 s of random actions (-1.9 cm at 360 Hz).
    pub ground_contact_hz: f32,
    /// Largest velocity used to push penetrating bodies apart, m/s
    /// (PhysX `max_depenetration_velocity` 10 in SkillMimic-V2's configs).
    pub max_depenetration_velocity: f32,
    /// Angular damping of humanoid bodies (SkillMimic-V2 asset option 0.01, docs/simulation.md).
    pub angular_damping: f32,
    /// Frame of root and object angular velocities in [`State`].
    pub angvel_frame: AngvelFrame,
    /// Contact prediction distance, m (rapier's default 0.02): contacts
    /// are created this far ahead. Limbs move up to 20 m/s (17 cm per
    /// physics step) under random actions; with 0.02 alone a limb's contact
    /// came a step late and forearms, toes and fingers sank up to 6 cm into
    /// the ground. 0.1 removed those but made every pair within 10 cm a
    /// solver contact (all of a hand's fingers, arms beside the trunk); 0.05
    /// with `soft_ccd` (fast bodies predict as far as they move) keeps the
    /// ground penetration within 2 cm and steps the full model about 1.3x
    /// faster (`skillaug bench sim`, docs/simulation.md).
    pub prediction_distance: f32,
    /// Soft CCD of humanoid bodies and objects, m (0 disables; rapier's
    /// `soft_ccd_prediction`): a pair's contacts are predicted as far ahead
    /// as the bodies move in a step (their relative linear speed times dt,
    /// at most this distance), when that exceeds `prediction_distance`.
    pub soft_ccd: f32,
    /// Factor on every joint's MJCF stiffness kp, damping kd unchanged
    /// (1 = the model's gains, as SkillMimic-V2's Isaac Gym asset uses
    /// them). rapier's implicit motor closes a position error at the rate
    /// kp / (dt kp + kd) (`MotorModel::combine_coefficients`), so the drive's
    /// time constant, kd/kp = 0.1 s for every BallPlay joint, becomes
    /// 0.1 s / factor; a factor on kp and kd alike would leave it as it is
    /// (`train.pd_stiffness_scale`, docs/simulation.md).
    pub pd_stiffness_scale: f32,
}

impl Default for SimOptions {
    fn default() -> Self {
        SimOptions {
            physics_hz: 120.0,
            substeps: 2,
            solver_iterations: 4,
            pgs_iterations: 4,
            stabilization_iterations: 1,
            contact_recycling: true,
            armature_inertia: true,
            min_mass: 0.5,
            hand_min_mass: 0.05,
            self_collision: true,
            hand_self_collision: true,
            friction: 1.0,
            ground_restitution: 0.8,
            ground_contact_hz: 600.0,
            max_depenetration_velocity: 10.0,
            angular_damping: 0.01,
            angvel_frame: AngvelFrame::Body,
            prediction_distance: 0.05,
            soft_ccd: 0.2,
            pd_stiffness_scale: 1.0,
        }
    }
}

impl crate::config::Validate for SimOptions {
    /// Rates and counts positive and bounded (a zero or infinite step would
    /// turn a run of seconds into no steps or into `usize::MAX` of them),
    /// coefficients finite and non-negative, restitution in [0, 1].
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.range("physics_hz", self.physics_hz, 1.0, 100_000.0)?;
        c.count("substeps", self.substeps as u64, 1, 1000)?;
        c.count("solver_iterations", self.solver_iterations as u64, 1, 1000)?;
        c.count("pgs_iterations", self.pgs_iterations as u64, 1, 1000)?;
        c.count(
            "stabilization_iterations",
            self.stabilization_iterations as u64,
            0,
            1000,
        )?;
        c.range("min_mass", self.min_mass as f64, 0.0, 1e4)?;
        c.range("hand_min_mass", self.hand_min_mass as f64, 0.0, 1e4)?;
        c.non_negative("friction", self.friction as f64)?;
        c.range(
            "ground_restitution",
            self.ground_restitution as f64,
            0.0,
            1.0,
        )?;
        c.positive("ground_contact_hz", self.ground_contact_hz as f64)?;
        c.positive(
            "max_depenetration_velocity",
            self.max_depenetration_velocity as f64,
        )?;
        c.non_negative("angular_damping", self.angular_damping as f64)?;
        c.range(
            "prediction_distance",
            self.prediction_distance as f64,
            0.0,
            1.0,
        )?;
        c.range("soft_ccd", self.soft_ccd as f64, 0.0, 10.0)?;
        c.range(
            "pd_stiffness_scale",
            self.pd_stiffness_scale as f64,
            0.1,
            100.0,
        )?;
        Ok(())
    }
}

impl SimOptions {
    /// Defaults for a data rate: 120 Hz physics and 2 substeps for 60 fps
    /// data, 60 Hz and 2 substeps for ParaHome's 30 fps.
    pub fn for_fps(fps: f64) -> SimOptions {
        SimOptions {
            physics_hz: 2.0 * fps,
            ..SimOptions::default()
        }
    }

    /// Policy step, s.
    pub fn policy_dt(&self) -> f32 {
        (self.substeps as f64 / self.physics_hz) as f32
    }
}

/// What a collider belongs to (stored in its `user_data`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Part {
    /// A humanoid body.
    Body(usize),
    /// An object.
    Object(usize),
    /// The ground.
    Ground,
}

const OBJECT_TAG: u128 = 1 << 32;
const GROUND_TAG: u128 = 1 << 33;

impl Part {
    fn tag(self) -> u128 {
        match self {
            Part::Body(i) => i as u128,
            Part::Object(k) => OBJECT_TAG | k as u128,
            Part::Ground => GROUND_TAG,
        }
    }

    fn of_tag(t: u128) -> Part {
        if t & GROUND_TAG != 0 {
            Part::Ground
        } else if t & OBJECT_TAG != 0 {
            Part::Object((t & 0xffff_ffff) as usize)
        } else {
            Part::Body(t as usize)
        }
    }
}

/// Contact forces and indicators after a step.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ContactReport {
    /// Net contact force on each humanoid body, world frame, N.
    pub body_force: Vec<[f32; 3]>,
    /// Net contact force on each object, N.
    pub object_force: Vec<[f32; 3]>,
    /// Object `k` touches a hand (wrist or finger) body.
    pub object_hands: Vec<bool>,
    /// Object `k` touches a non-hand humanoid body.
    pub object_body: Vec<bool>,
    /// A hand touches a non-hand body of the humanoid.
    pub body_hands: bool,
    /// `object_hands` at any physics substep of the policy step
    /// ([`World::step_with_contacts`]; else equal to `object_hands`).
    pub object_hands_any: Vec<bool>,
    /// `object_body` at any substep.
    pub object_body_any: Vec<bool>,
    /// `body_hands` at any substep.
    pub body_hands_any: bool,
    /// Smallest distance from a hand body's origin (wrist or finger joint)
    /// to object `k`'s centre over the substeps, m.
    pub object_hand_distance: Vec<f32>,
}

impl ContactReport {
    /// The reward's contact indicators (paper Eq. 17 and the rule of
    /// SkillMimic-V2 `skillmimic/env/tasks/skillmimic1.py`):
    /// object 0 against hands (by `detect`; `radius` in m for the
    /// proximity rule) and body, hands against body (touching at any
    /// substep, or at the last one for [`ContactDetect::TouchLast`]), and
    /// whether any of `penalty_bodies` feels a force component of at least
    /// 0.1 N after the last substep.
    pub fn reward_contacts(
        &self,
        penalty_bodies: &[usize],
        detect: ContactDetect,
        radius: f64,
    ) -> Contacts {
        let first = |v: &[bool]| v.first().copied().unwrap_or(false);
        let (ball_hands, ball_body, body_hands) = match detect {
            ContactDetect::Proximity => (
                self.object_hand_distance
                    .first()
                    .is_some_and(|d| (*d as f64) < radius),
                first(&self.object_body_any),
                self.body_hands_any,
            ),
            ContactDetect::Touch => (
                first(&self.object_hands_any),
                first(&self.object_body_any),
                self.body_hands_any,
            ),
            ContactDetect::TouchLast => (
                first(&self.object_hands),
                first(&self.object_body),
                self.body_hands,
            ),
        };
        Contacts {
            ball_hands,
            ball_body,
            body_hands,
            penalty_bodies: penalty_bodies
                .iter()
                .any(|&b| self.body_force[b].iter().any(|f| f.abs() >= 0.1)),
        }
    }
}

/// A pair touches when it pushes: contacts merely predicted (within
/// `prediction_distance`, not yet touching) carry no impulse.
fn touching(pair: &ContactPair) -> bool {
    pair.has_any_active_contact() && pair.total_impulse_magnitude() > 0.0
}

/// The humanoid's fixed description, shared by every world built from it.
#[derive(Clone, Debug)]
struct Skeleton {
    parents: Vec<Option<usize>>,
    offsets: Vec<Vector>,
    /// kp, kd of each joint's three axes (joint j drives body j + 1).
    gains: Vec<[[f32; 2]; 3]>,
    hand: Vec<bool>,
}

/// The object assist's spring ([`World::pull_object`]).
#[derive(Clone, Copy, Debug)]
pub struct Spring {
    /// Strength s, a fraction of the critically damped spring (0..=1).
    pub strength: f32,
    /// Natural frequency ω, rad/s.
    pub omega: f32,
    /// Dead band b, m: no force within this distance of the target
    /// position (0 = none).
    pub band: f32,
}

/// One world.
pub struct World {
    pw: PhysicsWorld,
    opts: SimOptions,
    sk: Skeleton,
    bodies: Vec<RigidBodyHandle>,
    joints: Vec<ImpulseJointHandle>,
    objects: Vec<RigidBodyHandle>,
    /// Motor targets currently set (exp-map triples).
    targets: Vec<f32>,
    /// Motor target velocities currently set, rad/s per motor axis (zero
    /// unless [`World::apply_action_with_rates`] set them).
    target_rates: Vec<f32>,
}

fn v3(a: [f64; 3]) -> Vector {
    Vector::new(a[0] as f32, a[1] as f32, a[2] as f32)
}

fn arr3(v: Vector) -> [f32; 3] {
    [v.x, v.y, v.z]
}

fn q4(q: Rotation) -> [f32; 4] {
    [q.x, q.y, q.z, q.w]
}

/// The rotation of the first four values of `a`, a quaternion (x, y, z, w)
/// taken as it is (not normalised).
pub fn rotation_of(a: &[f32]) -> Rotation {
    Rotation::from_xyzw(a[0], a[1], a[2], a[3])
}

/// [`rotation_of`] normalised: a unit rotation for the simulator.
fn unit_rotation_of(a: &[f32]) -> Rotation {
    rotation_of(a).normalize()
}

/// The vector of the first three values of `a`.
pub fn vector_of(a: &[f32]) -> Vector {
    Vector::new(a[0], a[1], a[2])
}

/// Motor target velocities (`[J*3]`, rad/s per motor axis) of joints whose
/// exp-maps `joint_rot` change at `joint_vel` (rad/s, as [`State`] holds
/// them): the relative angular velocity in the parent's frame,
/// `J_l(e) de/dt` ([`rot::jl_mul`]), which is what a motor axis's damping
/// term measures.
pub fn joint_rates(joint_rot: &[f32], joint_vel: &[f32]) -> Vec<f32> {
    joint_rot
        .chunks_exact(3)
        .zip(joint_vel.chunks_exact(3))
        .flat_map(|(e, de)| {
            let w = rot::jl_mul(vector_of(e), vector_of(de));
            [w.x, w.y, w.z]
        })
        .collect()
}

/// Bodies that belong to a hand: the wrists and everything below them.
pub fn hand_bodies(model: &Model) -> Vec<bool> {
    let mut hand = vec![false; model.bodies.len()];
    for (i, b) in model.bodies.iter().enumerate() {
        let own = b.name.contains("Wrist");
        hand[i] = own || b.parent.is_some_and(|p| hand[p]);
    }
    hand
}

fn geom_collider(g: &super::mjcf::Geom, body: &str) -> Result<ColliderBuilder> {
    let density = g.density.unwrap_or(1000.0) as f32;
    let pose = |pos: [f64; 3]| {
        let r = match g.quat {
            Some([w, x, y, z]) => Rotation::from_xyzw(x as f32, y as f32, z as f32, w as f32),
            None => Rotation::IDENTITY,
        };
        Pose::from_parts(v3(pos), r.normalize())
    };
    let c = match g.kind.as_str() {
        "capsule" => {
            let r = *g.size.first().unwrap_or(&0.0) as f32;
            let Some(ft) = g.fromto else {
                bail!("body `{body}`: a capsule without `fromto` is not supported");
            };
            ColliderBuilder::capsule_from_endpoints(
                v3([ft[0], ft[1], ft[2]]),
                v3([ft[3], ft[4], ft[5]]),
                r,
            )
        }
        "cylinder" => {
            let r = *g.size.first().unwrap_or(&0.0) as f32;
            let Some(ft) = g.fromto else {
                bail!("body `{body}`: a cylinder without `fromto` is not supported");
            };
            let (a, b) = (v3([ft[0], ft[1], ft[2]]), v3([ft[3], ft[4], ft[5]]));
            let d = b - a;
            // rapier's cylinder lies along y
            let r_axis = Rotation::from_rotation_arc(Vector::Y, d.normalize());
            ColliderBuilder::cylinder(0.5 * d.length(), r)
                .position(Pose::from_parts(0.5 * (a + b), r_axis))
        }
        "sphere" => {
            ColliderBuilder::ball(*g.size.first().unwrap_or(&0.0) as f32).position(pose(g.pos))
        }
        "box" => {
            if g.size.len() != 3 {
                bail!("body `{body}`: a box needs three half-sizes");
            }
            // positive: the MJCF reader refuses other sizes
            ColliderBuilder::cuboid(g.size[0] as f32, g.size[1] as f32, g.size[2] as f32)
                .position(pose(g.pos))
        }
        other => bail!("body `{body}`: geom type `{other}` is not supported"),
    };
    Ok(c.density(density))
}

/// Gravity's acceleration, m/s^2, along -z in every world (the reward's
/// ball-energy term uses it too, `crate::reward::Errors::oe`).
pub const GRAVITY: f64 = 9.81;

/// The PD target, rad, that [`World::apply_action`] sets for one action
/// value `a`: π·clamp(a, −1, 1) (Eq. 11's scaling, as the reference code's
/// `humanoid_task.py` maps actions to joint targets).
pub fn pd_target(a: f32) -> f32 {
    std::f32::consts::PI * a.clamp(-1.0, 1.0)
}

impl World {
    /// Build a world from a humanoid model and objects.
    pub fn new(model: &Model, objects: &[ObjectSpec], opts: &SimOptions) -> Result<World> {
        if model.bodies.is_empty() || model.bodies[0].parent.is_some() {
            bail!("the humanoid model has no root body");
        }
        crate::config::Validate::validate(opts, "sim")?;
        let mut pw = PhysicsWorld::new();
        pw.gravity = Vector::new(0.0, 0.0, -(GRAVITY as f32));
        let ip = &mut pw.integration_parameters;
        ip.set_inv_dt(opts.physics_hz as f32);
        ip.num_solver_iterations = opts.solver_iterations.max(1);
        ip.num_internal_pgs_iterations = opts.pgs_iterations.max(1);
        ip.num_internal_stabilization_iterations = opts.stabilization_iterations;
        ip.contact_recycling = opts.contact_recycling;
        ip.normalized_prediction_distance = opts.prediction_distance;
        ip.static_contact_softness.natural_frequency = opts.ground_contact_hz;
        ip.normalized_max_corrective_velocity = opts.max_depenetration_velocity;

        let hand = hand_bodies(model);
        let n = model.bodies.len();
        let mut sk = Skeleton {
            parents: model.bodies.iter().map(|b| b.parent).collect(),
            offsets: model.bodies.iter().map(|b| v3(b.pos)).collect(),
            gains: Vec::with_capacity(n - 1),
            hand,
        };

        // Bodies at the model's rest pose (body frames only offset).
        let mut world_pos = vec![Vector::ZERO; n];
        let mut bodies = Vec::with_capacity(n);
        for (i, b) in model.bodies.iter().enumerate() {
            if let Some(p) = b.parent {
                world_pos[i] = world_pos[p] + sk.offsets[i];
            }
            let rb = RigidBodyBuilder::dynamic()
                .translation(world_pos[i] + Vector::new(0.0, 0.0, 1.0))
                .angular_damping(opts.angular_damping)
                .soft_ccd_prediction(opts.soft_ccd)
                .can_sleep(false)
                .user_data(i as u128);
            let h = pw.bodies.insert(rb);
            for g in &b.geoms {
                let c = geom_collider(g, &b.name)?
                    .friction(opts.friction)
                    .user_data(Part::Body(i).tag());
                pw.colliders.insert_with_parent(c, h, &mut pw.bodies);
            }
            // model departures (module doc)
            pw.bodies[h].recompute_mass_properties_from_colliders(&pw.colliders);
            let mass = pw.bodies[h].mass();
            let com = pw.bodies[h].local_center_of_mass();
            let armature = b.hinges.first().map_or(0.0, |j| j.armature) as f32;
            let min_mass = if sk.hand[i] {
                opts.hand_min_mass
            } else {
                opts.min_mass
            };
            let extra_mass = (min_mass - mass).max(0.0);
            let extra_inertia = if opts.armature_inertia && i > 0 {
                armature
            } else {
                0.0
            };
            if extra_mass > 0.0 || extra_inertia > 0.0 {
                let body = &mut pw.bodies[h];
                body.set_additional_mass_properties(
                    MassProperties::new(com, extra_mass, Vector::splat(extra_inertia)),
                    false,
                );
                body.recompute_mass_properties_from_colliders(&pw.colliders);
            }
            bodies.push(h);
        }

        // Joints.
        let mut joints = Vec::with_capacity(n - 1);
        for (i, b) in model.bodies.iter().enumerate().skip(1) {
            if b.hinges.len() != 3 {
                bail!(
                    "body `{}` has {} hinges; every non-root body needs three (x, y, z)",
                    b.name,
                    b.hinges.len()
                );
            }
            let mut g = [[0f32; 2]; 3];
            for (a, h) in b.hinges.iter().enumerate() {
                let mut want = [0.0; 3];
                want[a] = 1.0;
                if h.axis != want {
                    bail!(
                        "joint `{}` has axis {:?}; the three hinges must be x, y, z in order",
                        h.name,
                        h.axis
                    );
                }
                let k = opts.pd_stiffness_scale;
                g[a] = [k * h.stiffness as f32, h.damping as f32];
            }
            let mut jb = SphericalJointBuilder::new()
                .local_anchor1(sk.offsets[i])
                .local_anchor2(Vector::ZERO)
                .contacts_enabled(false);
            for (a, axis) in [JointAxis::AngX, JointAxis::AngY, JointAxis::AngZ]
                .into_iter()
                .enumerate()
            {
                jb = jb
                    .motor_model(axis, MotorModel::ForceBased)
                    .motor_position(axis, 0.0, g[a][0], g[a][1]);
            }
            sk.gains.push(g);
            let parent = bodies[b.parent.expect("non-root body has a parent")];
            joints.push(pw.impulse_joints.insert(parent, bodies[i], jb, true));
        }

        // Collision groups: 1 = humanoid, 2 and 3 = the two hands (a wrist
        // starts a hand; its descendants are in it).
        let mut hand_group: Vec<Option<Group>> = vec![None; n];
        let mut wrists = 0;
        for i in 0..n {
            hand_group[i] = match sk.parents[i].and_then(|p| hand_group[p]) {
                Some(g) => Some(g),
                None if sk.hand[i] => {
                    wrists += 1;
                    Some(if wrists == 1 {
                        Group::GROUP_2
                    } else {
                        Group::GROUP_3
                    })
                }
                None => None,
            };
        }
        for (_, c) in pw.colliders.iter_mut() {
            let Part::Body(i) = Part::of_tag(c.user_data) else {
                continue;
            };
            let mut member = Group::GROUP_1;
            let mut filter = Group::ALL;
            if !opts.self_collision {
                filter ^= Group::GROUP_1;
            }
            if let Some(h) = hand_group[i] {
                member |= h;
                if !opts.hand_self_collision {
                    filter ^= h;
                }
            }
            c.set_collision_groups(InteractionGroups::new(
                member,
                filter,
                InteractionTestMode::And,
            ));
        }

        // Ground: the half-space z <= 0.
        let ground = pw.bodies.insert(RigidBodyBuilder::fixed());
        pw.colliders.insert_with_parent(
            ColliderBuilder::halfspace(rapier3d::na::Unit::new_unchecked(Vector::Z))
                .friction(opts.friction)
                .restitution(opts.ground_restitution)
                .user_data(Part::Ground.tag()),
            ground,
            &mut pw.bodies,
        );

        // Objects, parked beside the origin until a state is set.
        let mut objs = Vec::with_capacity(objects.len());
        for (k, o) in objects.iter().enumerate() {
            let h = pw.bodies.insert(
                RigidBodyBuilder::dynamic()
                    .translation(Vector::new(2.0 + k as f32, 0.0, 1.0))
                    .linear_damping(o.damping[0])
                    .angular_damping(o.damping[1])
                    .soft_ccd_prediction(opts.soft_ccd)
                    .can_sleep(false),
            );
            let collider = ColliderBuilder::new(o.shape.clone());
            // a shell ball: the solid sphere's mass, a shell's inertia
            let collider = match (o.inertia, o.sphere_mass_properties()) {
                (super::objects::BallInertia::Shell, Some((m, i))) => {
                    collider.mass_properties(MassProperties::new(Vector::ZERO, m, Vector::splat(i)))
                }
                _ => collider.density(o.density),
            };
            pw.colliders.insert_with_parent(
                collider
                    .restitution(o.restitution)
                    .friction(o.friction)
                    .user_data(Part::Object(k).tag()),
                h,
                &mut pw.bodies,
            );
            objs.push(h);
        }

        Ok(World {
            pw,
            opts: opts.clone(),
            targets: vec![0.0; 3 * (n - 1)],
            target_rates: vec![0.0; 3 * (n - 1)],
            sk,
            bodies,
            joints,
            objects: objs,
        })
    }

    /// Number of humanoid bodies.
    pub fn n_bodies(&self) -> usize {
        self.bodies.len()
    }

    /// Number of three-DoF joints (= action triples).
    pub fn n_joints(&self) -> usize {
        self.joints.len()
    }

    /// Number of objects.
    pub fn n_objects(&self) -> usize {
        self.objects.len()
    }

    /// Settings.
    pub fn options(&self) -> &SimOptions {
        &self.opts
    }

    /// Mass of each humanoid body, kg (after the model departures).
    pub fn body_masses(&self) -> Vec<f32> {
        self.bodies
            .iter()
            .map(|&h| self.pw.bodies[h].mass())
            .collect()
    }

    /// Mass of object `k`, kg.
    pub fn object_mass(&self, k: usize) -> f32 {
        self.pw.bodies[self.objects[k]].mass()
    }

    /// Hold a spring-damper force on object `k` towards position `p` (m)
    /// and velocity `v` (m/s), world frame, over the coming physics steps
    /// until [`World::release_object`]: F = s m (ω² (p' - x) + 2ω (v - ẋ))
    /// N, with s = `spring.strength`, ω = `spring.omega` rad/s, m the
    /// object's mass and x, ẋ its centre's position and velocity now (a
    /// critically damped spring of natural frequency ω at strength 1).
    /// p' = p without a dead band; with `spring.band` = b > 0 m no force
    /// acts while |p - x| <= b, and beyond it p' is the point of the
    /// band's sphere about p nearest to x. Returns whether a force was
    /// set. Training's object assist
    /// ([`crate::rl::humanoid::EnvConfig::object_assist`]).
    pub fn pull_object(&mut self, k: usize, p: [f32; 3], v: [f32; 3], spring: Spring) -> bool {
        let b = &mut self.pw.bodies[self.objects[k]];
        let (x, xd, m) = (b.center_of_mass(), b.linvel(), b.mass());
        let gap = vector_of(&p) - x;
        let dist = gap.length();
        if spring.band > 0.0 && dist <= spring.band {
            return false;
        }
        let reach = if spring.band > 0.0 {
            gap * (1.0 - spring.band / dist)
        } else {
            gap
        };
        let omega = spring.omega;
        let f =
            (omega * omega * reach + 2.0 * omega * (vector_of(&v) - xd)) * (spring.strength * m);
        b.reset_forces(true);
        b.add_force(f, true);
        true
    }

    /// Remove the force of [`World::pull_object`] from object `k`.
    pub fn release_object(&mut self, k: usize) {
        self.pw.bodies[self.objects[k]].reset_forces(false);
    }

    /// Set the motor targets: one exp-map triple per joint.
    pub fn set_joint_targets(&mut self, targets: &[f32]) {
        assert_eq!(
            targets.len(),
            self.targets.len(),
            "one target triple per joint"
        );
        for (j, t) in targets.chunks_exact(3).enumerate() {
            self.set_joint_target(j, [t[0], t[1], t[2]], [0.0; 3]);
        }
    }

    /// Set the targets from a policy action: target = pi * clamp(a, -1, 1)
    /// (docs/simulation.md).
    pub fn apply_action(&mut self, action: &[f32]) {
        self.apply(action, None);
    }

    /// [`World::apply_action`] with motor target velocities `rates` (`[J*3]`,
    /// rad/s per motor axis, [`joint_rates`]): each axis's torque becomes
    /// kp (target - q) + kd (rate - dq/dt) instead of kp (target - q) -
    /// kd dq/dt, so a target moving at `rate` is followed without the
    /// kd/kp (0.1 s for every joint of the BallPlay model) lag of a PD
    /// drive whose target velocity is zero.
    pub fn apply_action_with_rates(&mut self, action: &[f32], rates: &[f32]) {
        assert_eq!(rates.len(), self.targets.len(), "one rate per DoF");
        self.apply(action, Some(rates));
    }

    fn apply(&mut self, action: &[f32], rates: Option<&[f32]>) {
        assert_eq!(action.len(), self.targets.len(), "one action per DoF");
        let t = pd_target;
        for (j, a) in action.chunks_exact(3).enumerate() {
            let r = rates.map_or([0.0; 3], |r| [r[3 * j], r[3 * j + 1], r[3 * j + 2]]);
            self.set_joint_target(j, [t(a[0]), t(a[1]), t(a[2])], r);
        }
    }

    /// Set joint `j`'s motor target and target velocity; unchanged ones
    /// leave the joint alone (touching a joint makes rapier rebuild its
    /// solver caches).
    fn set_joint_target(&mut self, j: usize, t: [f32; 3], rate: [f32; 3]) {
        let (old, old_rate) = (
            &mut self.targets[3 * j..3 * j + 3],
            &mut self.target_rates[3 * j..3 * j + 3],
        );
        if *old == t && *old_rate == rate {
            return;
        }
        old.copy_from_slice(&t);
        old_rate.copy_from_slice(&rate);
        let angles = rot::motor_angles(vector_of(&t));
        let g = self.sk.gains[j];
        let joint = self
            .pw
            .impulse_joints
            .get_mut(self.joints[j], false)
            .expect("joint handle");
        for (a, axis) in [JointAxis::AngX, JointAxis::AngY, JointAxis::AngZ]
            .into_iter()
            .enumerate()
        {
            joint
                .data
                .set_motor(axis, angles[a], rate[a], g[a][0], g[a][1]);
        }
    }

    /// Current motor targets.
    pub fn joint_targets(&self) -> &[f32] {
        &self.targets
    }

    /// One physics step.
    pub fn step_physics(&mut self) {
        self.pw.step();
    }

    /// One policy step: `substeps` physics steps with the targets held.
    pub fn step(&mut self) {
        for _ in 0..self.opts.substeps {
            self.pw.step();
        }
    }

    /// [`World::step`], reading the contacts after every substep: the
    /// report's forces and `object_hands`/`object_body`/`body_hands` are
    /// those of the last substep, the `*_any` fields OR them over the
    /// substeps and `object_hand_distance` is the smallest over them.
    pub fn step_with_contacts(&mut self) -> ContactReport {
        let no = self.n_objects();
        let mut any_hands = vec![false; no];
        let mut any_body = vec![false; no];
        let mut any_bh = false;
        let mut dist = vec![f32::INFINITY; no];
        let mut last = ContactReport::default();
        for _ in 0..self.opts.substeps {
            self.pw.step();
            last = self.contacts();
            for k in 0..no {
                any_hands[k] |= last.object_hands[k];
                any_body[k] |= last.object_body[k];
                dist[k] = dist[k].min(last.object_hand_distance[k]);
            }
            any_bh |= last.body_hands;
        }
        last.object_hands_any = any_hands;
        last.object_body_any = any_body;
        last.body_hands_any = any_bh;
        last.object_hand_distance = dist;
        last
    }

    /// Hand-object separations, for checking what the contact solver sees:
    /// one row per pair of a collider of object `k` and a collider of a
    /// hand body, `(body, solver, geometry)`:
    /// - `body`: the hand body's model index;
    /// - `solver`: the smallest `dist` of the pair's contact points, m
    ///   (negative = penetration; `None`: no points), as the narrow phase
    ///   of the last physics step computed them from the poses before that
    ///   step moved the bodies;
    /// - `geometry`: parry's contact distance of the two shapes at their
    ///   bodies' current poses, m (infinite where parry cannot compare the
    ///   two shapes).
    ///
    /// The two columns of one call come from different poses: compare
    /// `geometry` read before a physics step with `solver` read after it.
    /// Without [`SimOptions::contact_recycling`] they agree; with it a pair
    /// that drifted less than 5 cm keeps its old points, so `solver` can
    /// lag by up to that drift. Empty without object `k`.
    pub fn hand_object_separations(&self, k: usize) -> Vec<(usize, Option<f32>, f32)> {
        let Some(&o) = self.objects.get(k) else {
            return Vec::new();
        };
        let cs = &self.pw.colliders;
        let mut rows = Vec::new();
        for &oc in self.pw.bodies[o].colliders() {
            for (i, &b) in self
                .bodies
                .iter()
                .enumerate()
                .filter(|(i, _)| self.sk.hand[*i])
            {
                for &hc in self.pw.bodies[b].colliders() {
                    let solver = self.pw.narrow_phase.contact_pair(hc, oc).and_then(|pair| {
                        pair.manifolds()
                            .iter()
                            .flat_map(|m| m.points.iter().map(|p| p.dist))
                            .reduce(f32::min)
                    });
                    let (h, ob) = (&cs[hc], &cs[oc]);
                    // from the bodies' poses: a collider's own follows its
                    // body's only once a step has run after `set_state`
                    let pose = |body: RigidBodyHandle, c: &Collider| {
                        *self.pw.bodies[body].position()
                            * c.position_wrt_parent().copied().unwrap_or(Pose::IDENTITY)
                    };
                    let geometry = rapier3d::parry::query::contact(
                        &pose(b, h),
                        h.shape(),
                        &pose(o, ob),
                        ob.shape(),
                        f32::MAX,
                    )
                    .ok()
                    .flatten()
                    .map_or(f32::INFINITY, |c| c.dist);
                    rows.push((i, solver, geometry));
                }
            }
        }
        rows
    }

    /// Smallest distance from a hand body's origin to object `k`'s centre, m.
    pub fn hand_distance(&self, k: usize) -> f32 {
        let o = self.pw.bodies[self.objects[k]].translation();
        self.bodies
            .iter()
            .zip(&self.sk.hand)
            .filter(|(_, h)| **h)
            .map(|(b, _)| (self.pw.bodies[*b].translation() - o).length())
            .fold(f32::INFINITY, f32::min)
    }

    fn world_angvel(&self, rot: Rotation, w: Vector) -> Vector {
        match self.opts.angvel_frame {
            AngvelFrame::World => w,
            AngvelFrame::Body => rot * w,
        }
    }

    fn state_angvel(&self, rot: Rotation, w: Vector) -> Vector {
        match self.opts.angvel_frame {
            AngvelFrame::World => w,
            AngvelFrame::Body => rot.inverse() * w,
        }
    }

    fn check_widths(&self, s: &State) -> Result<()> {
        let (j, o) = (3 * self.n_joints(), self.n_objects());
        let widths = [
            ("joint_rot", s.joint_rot.len(), j),
            ("joint_vel", s.joint_vel.len(), j),
            ("obj_pos", s.obj_pos.len(), 3 * o),
            ("obj_rot", s.obj_rot.len(), 4 * o),
            ("obj_linvel", s.obj_linvel.len(), 3 * o),
            ("obj_angvel", s.obj_angvel.len(), 3 * o),
        ];
        for (name, got, want) in widths {
            if got != want {
                bail!("state field `{name}` has {got} values; this world needs {want}");
            }
        }
        Ok(())
    }

    /// Place the humanoid and objects in state `s` (see the module doc).
    /// Joint motor targets are left as they are.
    pub fn set_state(&mut self, s: &State) -> Result<()> {
        self.check_widths(s)?;
        let n = self.n_bodies();
        let mut rot = vec![Rotation::IDENTITY; n];
        let mut pos = vec![Vector::ZERO; n];
        let mut w = vec![Vector::ZERO; n];
        let mut v = vec![Vector::ZERO; n];
        rot[0] = unit_rotation_of(&s.root_rot);
        pos[0] = vector_of(&s.root_pos);
        w[0] = self.world_angvel(rot[0], vector_of(&s.root_angvel));
        v[0] = vector_of(&s.root_linvel);
        for i in 1..n {
            let p = self.sk.parents[i].expect("parent");
            let e = vector_of(&s.joint_rot[3 * (i - 1)..]);
            let de = vector_of(&s.joint_vel[3 * (i - 1)..]);
            rot[i] = (rot[p] * rot::from_expmap(e)).normalize();
            pos[i] = pos[p] + rot[p] * self.sk.offsets[i];
            w[i] = w[p] + rot[p] * rot::jl_mul(e, de);
            v[i] = v[p] + w[p].cross(pos[i] - pos[p]);
        }
        for i in 0..n {
            let b = &mut self.pw.bodies[self.bodies[i]];
            b.set_position(Pose::from_parts(pos[i], rot[i]), true);
            let com = pos[i] + rot[i] * b.local_center_of_mass();
            b.set_linvel(v[i] + w[i].cross(com - pos[i]), true);
            b.set_angvel(w[i], true);
        }
        for k in 0..self.n_objects() {
            let r = unit_rotation_of(&s.obj_rot[4 * k..]);
            let p = vector_of(&s.obj_pos[3 * k..]);
            let wk = self.world_angvel(r, vector_of(&s.obj_angvel[3 * k..]));
            let b = &mut self.pw.bodies[self.objects[k]];
            b.set_position(Pose::from_parts(p, r), true);
            let com = p + r * b.local_center_of_mass();
            b.set_linvel(vector_of(&s.obj_linvel[3 * k..]) + wk.cross(com - p), true);
            b.set_angvel(wk, true);
        }
        // forget joint impulses of the previous episode (warm start)
        for (_, j) in self.pw.impulse_joints.iter_mut() {
            j.impulses = Default::default();
        }
        Ok(())
    }

    /// Make every humanoid body kinematic (moved by the velocities last set,
    /// pushing objects without being pushed back: an infinitely strong
    /// body) or dynamic again, for diagnostics (`skillaug check-ball`).
    pub fn humanoid_kinematic(&mut self, on: bool) {
        let t = if on {
            RigidBodyType::KinematicVelocityBased
        } else {
            RigidBodyType::Dynamic
        };
        for &b in &self.bodies {
            self.pw.bodies[b].set_body_type(t, true);
        }
    }

    /// Hold the root body in place (fixed) or let it move (dynamic), for
    /// drive tests and diagnostics.
    pub fn pin_root(&mut self, pinned: bool) {
        let t = if pinned {
            RigidBodyType::Fixed
        } else {
            RigidBodyType::Dynamic
        };
        self.pw.bodies[self.bodies[0]].set_body_type(t, true);
    }

    /// The lowest point of any humanoid or object collider (z of the
    /// bounding boxes), m, and what it belongs to: below 0 means
    /// penetration into the ground.
    pub fn lowest_point(&self) -> (f32, Part) {
        self.pw
            .colliders
            .iter()
            .map(|(_, c)| (c.compute_aabb().mins.z, Part::of_tag(c.user_data)))
            .filter(|(_, p)| *p != Part::Ground)
            .fold(
                (f32::INFINITY, Part::Ground),
                |a, b| if b.0 < a.0 { b } else { a },
            )
    }

    /// The largest linear speed of any humanoid body's centre of mass or
    /// object, m/s, and whether every body's pose and velocity is finite.
    pub fn max_speed(&self) -> (f32, bool) {
        let mut finite = true;
        let mut max = 0f32;
        for &h in self.bodies.iter().chain(&self.objects) {
            let b = &self.pw.bodies[h];
            let v = b.linvel();
            finite &= v.is_finite() && b.angvel().is_finite() && b.translation().is_finite();
            max = max.max(v.length());
        }
        (max, finite)
    }

    /// Separation of the joint anchors, m: how far each child's origin is
    /// from where its parent's frame places it (0 for an exactly solved
    /// joint). Returns the mean and the largest over all joints.
    pub fn joint_gap(&self) -> (f32, f32) {
        let (mut sum, mut max) = (0f32, 0f32);
        for (i, &h) in self.bodies.iter().enumerate().skip(1) {
            let p = &self.pw.bodies[self.bodies[self.sk.parents[i].expect("non-root body")]];
            let want = p.position() * self.sk.offsets[i];
            let gap = (self.pw.bodies[h].translation() - want).length();
            sum += gap;
            max = max.max(gap);
        }
        (sum / (self.bodies.len() - 1).max(1) as f32, max)
    }

    /// Height of the root body, m.
    pub fn root_height(&self) -> f32 {
        self.pw.bodies[self.bodies[0]].translation().z
    }

    /// World-frame angular velocity of object `k`, rad/s.
    pub fn object_angvel_world(&self, k: usize) -> [f32; 3] {
        arr3(self.pw.bodies[self.objects[k]].angvel())
    }

    /// World rotation of body `i`.
    pub fn body_rotation(&self, i: usize) -> [f32; 4] {
        q4(*self.pw.bodies[self.bodies[i]].rotation())
    }

    /// World rotations `[B*4]` and angular velocities `[B*3]` of every body
    /// (what the observation needs beyond [`State`]).
    pub fn body_frames(&self, rot: &mut Vec<f32>, angvel: &mut Vec<f32>) {
        rot.clear();
        angvel.clear();
        for &h in &self.bodies {
            let b = &self.pw.bodies[h];
            rot.extend_from_slice(&q4(*b.rotation()));
            angvel.extend_from_slice(&arr3(b.angvel()));
        }
    }

    /// The current state in the layout of the ingested frames. `contact` is
    /// true when object 0 touches the humanoid.
    pub fn get_state(&self) -> State {
        let n = self.n_bodies();
        let mut s = State {
            joint_rot: Vec::with_capacity(3 * (n - 1)),
            joint_vel: Vec::with_capacity(3 * (n - 1)),
            body_pos: Vec::with_capacity(3 * n),
            body_vel: Vec::with_capacity(3 * n),
            ..State::default()
        };
        let frames: Vec<(Vector, Rotation, Vector, Vector)> = self
            .bodies
            .iter()
            .map(|&h| {
                let b = &self.pw.bodies[h];
                let p = b.translation();
                (p, *b.rotation(), b.velocity_at_point(p), b.angvel())
            })
            .collect();
        let (p0, r0, v0, w0) = frames[0];
        s.root_pos = arr3(p0);
        s.root_rot = q4(r0);
        s.root_rot_expmap = arr3(rot::to_expmap(r0));
        s.root_linvel = arr3(v0);
        s.root_angvel = arr3(self.state_angvel(r0, w0));
        for i in 1..n {
            let p = self.sk.parents[i].expect("parent");
            let (_, rp, _, wp) = frames[p];
            let (_, rc, _, wc) = frames[i];
            let e = rot::to_expmap(rp.inverse() * rc);
            let de = rot::jl_inv_mul(e, rp.inverse() * (wc - wp));
            s.joint_rot.extend_from_slice(&arr3(e));
            s.joint_vel.extend_from_slice(&arr3(de));
        }
        for &(p, _, v, _) in &frames {
            s.body_pos.extend_from_slice(&arr3(p));
            s.body_vel.extend_from_slice(&arr3(v));
        }
        for &h in &self.objects {
            let b = &self.pw.bodies[h];
            let p = b.translation();
            let r = *b.rotation();
            s.obj_pos.extend_from_slice(&arr3(p));
            s.obj_rot.extend_from_slice(&q4(r));
            s.obj_linvel
                .extend_from_slice(&arr3(b.velocity_at_point(p)));
            s.obj_angvel
                .extend_from_slice(&arr3(self.state_angvel(r, b.angvel())));
        }
        s.contact = self.object_touches_humanoid(0);
        s
    }

    /// Whether object `k` touches a humanoid body (false without object `k`).
    fn object_touches_humanoid(&self, k: usize) -> bool {
        let Some(&h) = self.objects.get(k) else {
            return false;
        };
        let colliders = &self.pw.colliders;
        self.pw.bodies[h].colliders().iter().any(|&c| {
            self.pw.narrow_phase.contact_pairs_with(c).any(|pair| {
                let other = if pair.collider1 == c {
                    pair.collider2
                } else {
                    pair.collider1
                };
                touching(pair)
                    && colliders
                        .get(other)
                        .is_some_and(|o| matches!(Part::of_tag(o.user_data), Part::Body(_)))
            })
        })
    }

    /// Contact forces and indicators of the last physics step.
    pub fn contacts(&self) -> ContactReport {
        let n = self.n_bodies();
        let no = self.n_objects();
        let mut r = ContactReport {
            body_force: vec![[0.0; 3]; n],
            object_force: vec![[0.0; 3]; no],
            object_hands: vec![false; no],
            object_body: vec![false; no],
            body_hands: false,
            ..ContactReport::default()
        };
        let inv_dt = self.pw.integration_parameters.inv_dt();
        let colliders = &self.pw.colliders;
        for pair in self.pw.narrow_phase.contact_pairs() {
            if !touching(pair) {
                continue;
            }
            let (Some(c1), Some(c2)) =
                (colliders.get(pair.collider1), colliders.get(pair.collider2))
            else {
                continue;
            };
            let (a, b) = (Part::of_tag(c1.user_data), Part::of_tag(c2.user_data));
            // the impulse pushes collider2 along the normal, collider1 against it
            let f = pair.total_impulse() * inv_dt;
            let mut add = |part: Part, f: Vector| match part {
                Part::Body(i) => {
                    let t = &mut r.body_force[i];
                    *t = [t[0] + f.x, t[1] + f.y, t[2] + f.z];
                }
                Part::Object(k) => {
                    let t = &mut r.object_force[k];
                    *t = [t[0] + f.x, t[1] + f.y, t[2] + f.z];
                }
                Part::Ground => {}
            };
            add(a, -f);
            add(b, f);
            for (x, y) in [(a, b), (b, a)] {
                match (x, y) {
                    (Part::Object(k), Part::Body(i)) => {
                        if self.sk.hand[i] {
                            r.object_hands[k] = true;
                        } else {
                            r.object_body[k] = true;
                        }
                    }
                    (Part::Body(i), Part::Body(j)) if self.sk.hand[i] && !self.sk.hand[j] => {
                        r.body_hands = true;
                    }
                    _ => {}
                }
            }
        }
        r.object_hands_any = r.object_hands.clone();
        r.object_body_any = r.object_body.clone();
        r.body_hands_any = r.body_hands;
        r.object_hand_distance = (0..no).map(|k| self.hand_distance(k)).collect();
        r
    }
}
