//! Simulated ball flights in the reference (`train.reference_ball =
//! "simulated"`).
//!
//! A captured dribble's ball does not fly as the simulated ball does. The
//! DF clips' ball keeps about half of its horizontal speed through the
//! bounce (3.4 m/s before, 1.6-1.7 m/s after), the simulated one, landing
//! without spin, about 0.78 of it (docs/training.md, "A ball whose spin
//! dies away"). So a simulated ball that leaves the hand exactly as the
//! clip's does comes back ahead of the clip's ball at the frame where the
//! clip's hand meets it again (by 0.10-0.28 m in DF): no push can both
//! match the reference's release and reach its catch.
//!
//! This module makes the reference's flights physically consistent. For
//! every flight of a ball clip ([`flight_frames`]: from the release, the
//! first frame without a hand on the ball after one with a hand on the
//! descending ball, to the catch, the next frame with a hand on it, with a
//! bounce between) it finds the release velocity `v` with which the ball,
//! alone in the simulated world (the humanoid kinematic and far away),
//! started at the clip's release frame from the clip's position without
//! spin, is at the clip's catch position at the catch frame (Newton's
//! method on the 3 x 3 system, with a forward-difference Jacobian and
//! halved steps that keep the flight's one bounce), and replaces the
//! clip's ball over the frames after the release up to the one before the
//! catch with that flight: positions, orientations, linear and angular
//! velocities. The release frame keeps its position and orientation and
//! gets the found velocity and no spin; the catch frame keeps the clip's
//! ball (so its orientation and spin jump back to the clip's there; the
//! other frames keep the ingest's backward-difference velocities). The
//! humanoid's frames and the contact flags are untouched. A
//! flight that cannot be solved to within [`MISS_TOLERANCE`], or only
//! without the clip's bounce, keeps the clip's ball.
//!
//! Not in the paper or the reference code: it corrects the captured ball
//! as SkillMimic-V2's augmentations correct sparse and noisy
//! demonstrations, on the ball's flight alone (its contacts with the hand
//! stay the policy's to find). Measured figures: docs/training.md ("A
//! reference ball that flies as the simulated one does").

use super::push::{hand_near, Scene};
use super::world::{hand_bodies, World};
use crate::motion::clip::ClipFrames;
use crate::motion::quat::quat_to_expmap;
use crate::motion::{MotionLib, State};
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

/// Which ball the training reference follows between a push's release
/// and its catch (`train.reference_ball`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ReferenceBall {
    /// The clip's captured ball (the paper's and the reference code's).
    #[default]
    Captured,
    /// Simulated flights that reach the clip's catch (module doc).
    Simulated,
}

impl ReferenceBall {
    /// The setting's value as written in a recipe.
    pub fn name(self) -> &'static str {
        match self {
            ReferenceBall::Captured => "captured",
            ReferenceBall::Simulated => "simulated",
        }
    }
}

/// Largest distance, m, between the solved flight's ball and the clip's
/// at the catch frame for the flight to replace the clip's.
pub const MISS_TOLERANCE: f64 = 0.01;

/// Newton iterations at most.
const ITERATIONS: usize = 30;

/// Step of the forward-difference Jacobian, m/s.
const DV: f64 = 1e-2;

/// How far the humanoid is moved away along x while the ball flies, m.
const AWAY: f32 = 100.0;

/// One push window's flight, as solved.
#[derive(Clone, Debug, PartialEq)]
pub struct Flight {
    /// Clip index in the library.
    pub clip: usize,
    /// The window's release frame (the flight's first).
    pub release: usize,
    /// The catch frame (the flight ends at it).
    pub catch: usize,
    /// The clip's ball velocity at the release, m/s.
    pub v_clip: [f64; 3],
    /// The solved release velocity, m/s.
    pub v_sim: [f64; 3],
    /// Distance at the catch frame between the clip's ball and a simulated
    /// ball released with the clip's velocity, m.
    pub miss_clip: f64,
    /// The same with the solved velocity, m.
    pub miss_sim: f64,
    /// How often the solved flight's ball turns from falling to rising
    /// (its bounces; the clip's flight has one).
    pub bounces: usize,
    /// Whether the flight replaced the clip's ball: `miss_sim <=`
    /// [`MISS_TOLERANCE`] and one bounce, as the clip's (a release
    /// upwards can also reach the catch, without a bounce).
    pub applied: bool,
}

/// Replace the ball flights of `clips` in `lib` by simulated ones (module
/// doc), in `scene`'s physics; returns every window's [`Flight`] (none for
/// clips whose object 0 is not the ball). A hand holds the ball while a
/// hand body's origin is within `hand_radius` m of its centre
/// ([`flight_frames`]; training uses the push search's 0.15 m,
/// [`super::push::PushConfig`]).
///
/// # Errors
/// A world that cannot be built or a clip frame it refuses, naming the clip
/// and the window.
pub fn simulate_flights(
    lib: &mut MotionLib,
    clips: &[usize],
    scene: Scene<'_>,
    hand_radius: f64,
) -> Result<Vec<Flight>> {
    if scene.objects.first().is_none_or(|o| o.name != "ball") {
        return Ok(Vec::new());
    }
    let hand = hand_bodies(scene.model);
    let mut out = Vec::new();
    for &clip in clips {
        for (release, catch) in flight_frames(&lib.frames[clip], &hand, hand_radius) {
            let name = &lib.clips[clip].name;
            let f = &mut lib.frames[clip];
            let flight = solve(f, scene, release, catch)
                .with_context(|| {
                    format!(
                        "train.reference_ball: clip {clip} ({name}), flight from frame {release} \
                         to {catch}"
                    )
                })
                .map(|(mut fl, states)| {
                    fl.clip = clip;
                    if fl.applied {
                        write_flight(f, release, &states);
                    }
                    fl
                })?;
            out.push(flight);
        }
    }
    Ok(out)
}

/// The flights of clip `f` as `(release, catch)` frame pairs: a release
/// is a frame where no hand body origin (`hand` marks the hand bodies) is
/// within `hand_radius` m of object 0's centre, after a frame where one is
/// while the ball descends; its catch is the next frame where one is again,
/// and between them the ball bounces (its vertical velocity turns from
/// below 0 to above 0). Every frame from the one before the release to
/// the catch is valid. None when `f` has no object.
pub fn flight_frames(f: &ClipFrames, hand: &[bool], hand_radius: f64) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    if f.n_objects == 0 {
        return out;
    }
    let near = |s: &State| hand_near(s, hand, hand_radius);
    let mut i = 1;
    while i < f.frames {
        let (Some(before), Some(at)) = (f.state(i - 1), f.state(i)) else {
            i += 1;
            continue;
        };
        if !(near(&before) && before.obj_linvel[2] < 0.0 && !near(&at)) {
            i += 1;
            continue;
        }
        let mut descended = at.obj_linvel[2] < 0.0;
        let mut bounced = false;
        let mut catch = None;
        let mut j = i + 1;
        while j < f.frames {
            let Some(s) = f.state(j) else { break };
            if near(&s) {
                catch = Some(j);
                break;
            }
            bounced |= descended && s.obj_linvel[2] > 0.0;
            descended |= s.obj_linvel[2] < 0.0;
            j += 1;
        }
        if let (Some(c), true) = (catch, bounced) {
            out.push((i, c));
        }
        i = j.max(i + 1);
    }
    out
}

/// The ball's states at frames `release..catch` (one per frame, the first
/// the release itself) of a ball released at `release` with velocity `v`.
struct Flown {
    states: Vec<State>,
    at_catch: [f64; 3],
    bounces: usize,
}

/// Solve one flight of `f` (module doc): the [`Flight`] (its `clip` left
/// 0) and the simulated states of frames `release..catch`.
fn solve(
    f: &ClipFrames,
    scene: Scene<'_>,
    release: usize,
    catch: usize,
) -> Result<(Flight, Vec<State>)> {
    let start = f.state(release).context("the release frame is missing")?;
    let target = f.state(catch).context("the catch frame is missing")?;
    let p_catch: [f64; 3] = std::array::from_fn(|k| target.obj_pos[k] as f64);
    let v_clip: [f64; 3] = std::array::from_fn(|k| start.obj_linvel[k] as f64);
    let mut world = World::new(scene.model, scene.objects, scene.opts)?;
    let mut away = start.clone();
    away.root_pos[0] += AWAY;
    away.root_linvel = [0.0; 3];
    away.root_angvel = [0.0; 3];
    away.joint_vel.fill(0.0);
    let frames = catch - release;
    // the humanoid stays put, away and still, for every flight
    world.set_state(&away)?;
    world.humanoid_kinematic(true);
    let mut fly = |v: [f64; 3]| -> Result<Flown> {
        let mut s = away.clone();
        for (o, x) in s.obj_linvel.iter_mut().zip(v) {
            *o = x as f32;
        }
        s.obj_angvel[..3].fill(0.0);
        world.set_state(&s)?;
        // frames release..=catch, one step apart
        let mut states = vec![world.get_state()];
        for _ in 0..frames {
            world.step();
            states.push(world.get_state());
        }
        let bounces = states
            .windows(2)
            .filter(|w| w[0].obj_linvel[2] < 0.0 && w[1].obj_linvel[2] > 0.0)
            .count();
        let end = states.pop().expect("the catch frame's state");
        Ok(Flown {
            states,
            at_catch: std::array::from_fn(|k| end.obj_pos[k] as f64),
            bounces,
        })
    };
    let miss = |a: &[f64; 3]| -> [f64; 3] { std::array::from_fn(|k| a[k] - p_catch[k]) };
    let norm = |r: &[f64; 3]| r.iter().map(|x| x * x).sum::<f64>().sqrt();
    let mut v = v_clip;
    let mut flown = fly(v)?;
    let mut r = miss(&flown.at_catch);
    let miss_clip = norm(&r);
    for _ in 0..ITERATIONS {
        if norm(&r) <= MISS_TOLERANCE * 0.1 {
            break;
        }
        // forward-difference Jacobian d p_catch / d v
        let mut jac = [[0f64; 3]; 3];
        for j in 0..3 {
            let mut vj = v;
            vj[j] += DV;
            let pj = fly(vj)?.at_catch;
            for i in 0..3 {
                jac[i][j] = (pj[i] - flown.at_catch[i]) / DV;
            }
        }
        let Some(step) = solve3(jac, r) else { break };
        // halve the step until the miss shrinks (a bounce can bend the
        // map), keeping the one bounce once the flight has it
        let mut scale = 1.0;
        let mut improved = false;
        for _ in 0..8 {
            let cand: [f64; 3] = std::array::from_fn(|k| v[k] - scale * step[k]);
            let fc = fly(cand)?;
            let rc = miss(&fc.at_catch);
            // stay on the branch with the clip's one bounce
            let branch = fc.bounces == 1 || flown.bounces != 1;
            if branch && norm(&rc) < norm(&r) {
                v = cand;
                flown = fc;
                r = rc;
                improved = true;
                break;
            }
            scale *= 0.5;
        }
        if !improved {
            break;
        }
    }
    let miss_sim = norm(&r);
    let applied = miss_sim <= MISS_TOLERANCE && flown.bounces == 1;
    Ok((
        Flight {
            clip: 0,
            release,
            catch,
            v_clip,
            v_sim: v,
            miss_clip,
            miss_sim,
            bounces: flown.bounces,
            applied,
        },
        flown.states,
    ))
}

/// The solution of the 3 x 3 system `a x = b` (Cramer's rule), or `None`
/// when `a` is singular.
fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(a);
    if !d.is_finite() || d.abs() < 1e-12 {
        return None;
    }
    Some(std::array::from_fn(|j| {
        let mut m = a;
        for i in 0..3 {
            m[i][j] = b[i];
        }
        det(m) / d
    }))
}

/// Write object 0 of `states` (frames `release..release + states.len()`)
/// into `f`; the release frame keeps its position and orientation.
fn write_flight(f: &mut ClipFrames, release: usize, states: &[State]) {
    let o = f.n_objects;
    for (k, s) in states.iter().enumerate() {
        let i = release + k;
        if k > 0 {
            f.obj_pos[i * o * 3..i * o * 3 + 3].copy_from_slice(&s.obj_pos[..3]);
            f.obj_rot[i * o * 4..i * o * 4 + 4].copy_from_slice(&s.obj_rot[..4]);
            let q = [s.obj_rot[0], s.obj_rot[1], s.obj_rot[2], s.obj_rot[3]];
            f.obj_rot_expmap[i * o * 3..i * o * 3 + 3].copy_from_slice(&quat_to_expmap(q));
        }
        f.obj_linvel[i * o * 3..i * o * 3 + 3].copy_from_slice(&s.obj_linvel[..3]);
        f.obj_angvel[i * o * 3..i * o * 3 + 3].copy_from_slice(&s.obj_angvel[..3]);
    }
}
