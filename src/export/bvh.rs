//! BVH export: one character's motion as a Biovision Hierarchy text file.
//!
//! # Format
//! The Biovision BVH format as publicly documented (Biovision's original
//! description, as explained in M. Meredith and S. Maddock, "Motion Capture
//! File Formats Explained", Univ. of Sheffield, 2001): a
//! `HIERARCHY` section of nested `ROOT` / `JOINT` blocks, each with an
//! `OFFSET` from its parent and its `CHANNELS`, `End Site` blocks closing the
//! chains, then a `MOTION` section with `Frames:`, `Frame Time:` (seconds)
//! and one line of channel values per frame, in the order the channels
//! appear in the hierarchy. A joint's transform is
//! `T(OFFSET) * R(channels)`, composed from the root down, and the rotation
//! channels compose in the order listed, so `Zrotation Xrotation Yrotation`
//! means `R = Rz(z) * Rx(x) * Ry(y)` acting on column vectors (intrinsic
//! z, then x', then y'').
//!
//! # What this file holds
//! * The MJCF humanoid's bodies, in model (depth-first) order: the root body
//!   is the `ROOT` with `CHANNELS 6 Xposition Yposition Zposition Zrotation
//!   Xrotation Yrotation`, every other body a `JOINT` with `CHANNELS 3
//!   Zrotation Xrotation Yrotation`; joint names are the body names.
//! * `OFFSET` of a joint: the body's `pos` in its parent's frame (the MJCF
//!   offset), in the chosen unit ([`Units`]). The root's `OFFSET` is zero:
//!   its position channels carry its whole world position.
//! * `End Site` of a leaf body: the far end of its geoms (the tip of a
//!   finger capsule, the centre of the head sphere), or half the body's own
//!   offset where its geoms sit at its origin (the toe boxes), so tools that
//!   draw bones draw them with a length; it carries no motion.
//! * Rotation angles in degrees. A joint's rotation is its local rotation
//!   relative to its parent, the simulator's exp-map converted to
//!   `Rz * Rx * Ry` Euler angles. Each frame picks, of the two Euler triples
//!   of a rotation and their 360-degree turns, the one nearest the previous
//!   frame, so the curves stay continuous (no wrap at +-180, and a middle
//!   angle may pass +-90) for tools that interpolate them.
//! * Missing frames (`None`) hold the last valid posture (before the first
//!   valid frame: the first valid posture), as the viewer plays them.
//!
//! # Axes
//! The simulator's world is z up (metres); BVH tools mostly assume y up, so
//! the world is converted to y up by the rotation `C` of -90 degrees about
//! x: `(x, y, z) -> (x, z, -y)` (simulator +z becomes +Y, simulator +y
//! becomes -Z, x stays). Only the root carries world quantities: its
//! position becomes `C * p` and its rotation `C * R`. Offsets and joint
//! rotations are relative to the parent body's frame, which a change of
//! world basis does not touch, so they keep the MJCF body frames (in which
//! this humanoid stands along +y, so its rest pose stands upright in a
//! y-up tool). Every body's world pose in the file is then exactly `C`
//! times its simulator pose.
//!
//! # Why hand-written
//! crates.io has no maintained BVH writer: `bvh_anim` (0.4, 2019, "alpha
//! quality", pinned to old `bstr`/`lexical`/`smallvec` releases) reads and
//! writes but is unmaintained, and `bvh_anim_parser` only parses. The text
//! is a hundred lines of formatting, so it is written here.

use super::motions::Track;
use crate::motion::quat;
use crate::motion::state::Posture;
use crate::sim::mjcf::Model;
use anyhow::{bail, Result};
use std::f64::consts::PI;
use std::fmt::Write;

/// Length unit of a BVH file's offsets and root positions (`--units m|cm`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Units {
    /// Metres.
    #[value(name = "m")]
    Metres,
    /// Centimetres.
    #[value(name = "cm")]
    Centimetres,
}

impl Units {
    /// Length of one metre in this unit.
    pub fn per_metre(self) -> f64 {
        match self {
            Units::Metres => 1.0,
            Units::Centimetres => 100.0,
        }
    }
}

/// The z-up to y-up world rotation `C` (-90 degrees about x) as a unit
/// quaternion (x, y, z, w): `C * (x, y, z) = (x, z, -y)`.
pub const Z_UP_TO_Y_UP: quat::Quat = [
    -std::f64::consts::FRAC_1_SQRT_2,
    0.0,
    0.0,
    std::f64::consts::FRAC_1_SQRT_2,
];

/// A simulator (z-up) vector in y-up coordinates: `(x, z, -y)`.
pub fn y_up(v: [f64; 3]) -> [f64; 3] {
    [v[0], v[2], -v[1]]
}

/// The postures to write, one per frame of `track`: missing frames hold the
/// last valid posture (the first valid one before it). Each posture is
/// checked against a model of `bodies` bodies (`3 * (bodies - 1)` joint
/// values) and `objects` objects (at least that many positions and rotations).
///
/// # Errors
/// A track without a valid frame, or a posture of another shape.
pub(crate) fn held(track: &Track, bodies: usize, objects: usize) -> Result<Vec<&Posture>> {
    let Some(first) = track.frames.iter().flatten().next() else {
        bail!("`{}` has no valid frame to export", track.name);
    };
    let mut last = first;
    let mut out = Vec::with_capacity(track.frames.len());
    for (i, f) in track.frames.iter().enumerate() {
        if let Some(p) = f {
            if p.joint_rot.len() != 3 * bodies.saturating_sub(1) {
                bail!(
                    "`{}` frame {i}: {} joint values for a model of {} bodies ({} expected)",
                    track.name,
                    p.joint_rot.len(),
                    bodies,
                    3 * bodies.saturating_sub(1)
                );
            }
            if p.obj_pos.len() < 3 * objects || p.obj_rot.len() < 4 * objects {
                bail!(
                    "`{}` frame {i}: {} object positions and {} rotations for {objects} objects",
                    track.name,
                    p.obj_pos.len() / 3,
                    p.obj_rot.len() / 4
                );
            }
            let finite = p.root_pos.iter().chain(&p.root_rot).all(|v| v.is_finite())
                && p.joint_rot.iter().all(|v| v.is_finite());
            if !finite {
                bail!(
                    "`{}` frame {i}: a root or joint value is not finite",
                    track.name
                );
            }
            last = p;
        }
        out.push(last);
    }
    Ok(out)
}

/// A unit quaternion (x, y, z, w) of `q` (f32 storage), normalised in f64.
pub(crate) fn unit(q: [f32; 4]) -> quat::Quat {
    let q = q.map(|v| v as f64);
    if quat::dot(q, q).sqrt() < 1e-12 {
        return quat::IDENTITY;
    }
    quat::normalize(q)
}

/// Rotation matrix (row-major, acting on column vectors) of a unit quaternion.
fn matrix(q: quat::Quat) -> [[f64; 3]; 3] {
    let [x, y, z, w] = q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// Euler angles `[z, x, y]` (radians) with `R(q) = Rz(z) * Rx(x) * Ry(y)`,
/// the middle angle in [-pi/2, pi/2] (at +-pi/2, where only `z +- y` is
/// fixed, `y` = 0).
pub fn zxy_from_quat(q: quat::Quat) -> [f64; 3] {
    let m = matrix(q);
    // R = [[cz cy - sz sx sy, -sz cx, cz sy + sz sx cy],
    //      [sz cy + cz sx sy,  cz cx, sz sy - cz sx cy],
    //      [-cx sy,            sx,    cx cy]]
    let cx = m[0][1].hypot(m[1][1]);
    let x = m[2][1].atan2(cx);
    if cx > 1e-9 {
        [(-m[0][1]).atan2(m[1][1]), x, (-m[2][0]).atan2(m[2][2])]
    } else {
        // gimbal lock: R = Rz(z -+ y) * Rx(+-pi/2); take y = 0
        [m[1][0].atan2(m[0][0]), x, 0.0]
    }
}

/// The unit quaternion of `Rz(a[0]) * Rx(a[1]) * Ry(a[2])` (radians).
pub fn quat_from_zxy(a: [f64; 3]) -> quat::Quat {
    let h = |axis: usize, t: f64| {
        let mut q = [0.0, 0.0, 0.0, (0.5 * t).cos()];
        q[axis] = (0.5 * t).sin();
        q
    };
    quat::mul(quat::mul(h(2, a[0]), h(0, a[1])), h(1, a[2]))
}

/// `v` plus the multiple of 2 pi that brings it nearest `like`.
fn unwrap(v: f64, like: f64) -> f64 {
    v + (2.0 * PI) * ((like - v) / (2.0 * PI)).round()
}

/// The Euler triple of `q` (as [`zxy_from_quat`]) nearest `prev`: of the
/// two triples of the rotation, `(z, x, y)` and `(z + pi, pi - x, y + pi)`,
/// each angle moved by whole turns towards `prev`, the nearer one.
pub fn zxy_near(q: quat::Quat, prev: Option<[f64; 3]>) -> [f64; 3] {
    let a = zxy_from_quat(q);
    let Some(p) = prev else { return a };
    let b = [a[0] + PI, PI - a[1], a[2] + PI];
    let near = |c: [f64; 3]| {
        let u = [unwrap(c[0], p[0]), unwrap(c[1], p[1]), unwrap(c[2], p[2])];
        let d: f64 = (0..3).map(|i| (u[i] - p[i]).powi(2)).sum();
        (d, u)
    };
    let (da, ua) = near(a);
    let (db, ub) = near(b);
    if db < da {
        ub
    } else {
        ua
    }
}

/// A name usable as a BVH joint name (no white space, not empty).
fn joint_name(name: &str, i: usize) -> String {
    let s: String = name
        .chars()
        .map(|c| {
            if c.is_whitespace() || c == '{' || c == '}' {
                '_'
            } else {
                c
            }
        })
        .collect();
    if s.is_empty() {
        format!("body{i}")
    } else {
        s
    }
}

/// The `End Site` offset of leaf body `b` (its frame, m): the geom point
/// farthest from the body origin (capsule and cylinder ends, sphere and box
/// centres), or half the body's own offset when that is under 1 mm.
fn end_site(model: &Model, b: usize) -> [f64; 3] {
    let body = &model.bodies[b];
    let mut best = [0.0; 3];
    let mut far = 0.0;
    for g in &body.geoms {
        let pts: Vec<[f64; 3]> = match g.fromto {
            Some(ft) => vec![[ft[0], ft[1], ft[2]], [ft[3], ft[4], ft[5]]],
            None => vec![g.pos],
        };
        for p in pts {
            let d = quat::norm(p);
            if d > far {
                far = d;
                best = p;
            }
        }
    }
    if far < 1e-3 {
        body.pos.map(|v| 0.5 * v)
    } else {
        best
    }
}

fn num(out: &mut String, v: f64, decimals: usize) {
    // no "-0.00000"
    let v = if v.abs() < 0.5 * 10f64.powi(-(decimals as i32)) {
        0.0
    } else {
        v
    };
    let _ = write!(out, "{v:.decimals$}");
}

/// The BVH text of one track at `fps` frames per second (module doc for the
/// layout, axes and angle conventions): offsets and root positions in
/// `units`, angles in degrees with five decimals, lengths with six (metres)
/// or four (centimetres) decimals, so that a body's position read back is
/// within a few micrometres of the simulator's forward kinematics.
///
/// # Errors
/// A track without a valid frame or with postures of another model, a
/// non-positive or non-finite `fps`, a model whose bodies are not in
/// depth-first order.
pub fn to_bvh(model: &Model, track: &Track, fps: f64, units: Units) -> Result<String> {
    if !(fps.is_finite() && fps > 0.0) {
        bail!("frame rate {fps} is not a positive number");
    }
    let nb = model.bodies.len();
    if nb == 0 || model.bodies[0].parent.is_some() {
        bail!("the model has no root body first");
    }
    // children in model order; the depth-first walk below must give model
    // order back, since the frame lines follow the hierarchy's order
    let mut children = vec![Vec::new(); nb];
    for (i, b) in model.bodies.iter().enumerate().skip(1) {
        match b.parent {
            Some(p) if p < i => children[p].push(i),
            _ => bail!(
                "body `{}` does not follow its parent (model not depth-first)",
                b.name
            ),
        }
    }
    let frames = held(track, nb, 0)?;
    let k = units.per_metre();
    let dec = match units {
        Units::Metres => 6,
        Units::Centimetres => 4,
    };

    let mut out = String::with_capacity(4096 + frames.len() * nb * 3 * 12);
    out.push_str("HIERARCHY\n");
    let mut order = Vec::with_capacity(nb);
    // explicit stack: (body, depth, closing?)
    let mut stack = vec![(0usize, 0usize, false)];
    while let Some((b, depth, close)) = stack.pop() {
        let ind = "\t".repeat(depth);
        if close {
            if children[b].is_empty() {
                let e = end_site(model, b);
                let _ = writeln!(out, "{ind}\tEnd Site\n{ind}\t{{");
                let _ = write!(out, "{ind}\t\tOFFSET");
                for v in e {
                    out.push(' ');
                    num(&mut out, v * k, dec);
                }
                let _ = writeln!(out, "\n{ind}\t}}");
            }
            let _ = writeln!(out, "{ind}}}");
            continue;
        }
        order.push(b);
        let body = &model.bodies[b];
        let name = joint_name(&body.name, b);
        if b == 0 {
            let _ = writeln!(out, "ROOT {name}\n{{");
            let _ = writeln!(out, "\tOFFSET {0} {0} {0}", format_args!("{:.dec$}", 0.0));
            out.push_str(
                "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n",
            );
        } else {
            let _ = writeln!(out, "{ind}JOINT {name}\n{ind}{{");
            let _ = write!(out, "{ind}\tOFFSET");
            for v in body.pos {
                out.push(' ');
                num(&mut out, v * k, dec);
            }
            let _ = writeln!(out, "\n{ind}\tCHANNELS 3 Zrotation Xrotation Yrotation");
        }
        stack.push((b, depth, true));
        for &c in children[b].iter().rev() {
            stack.push((c, depth + 1, false));
        }
    }
    if order.iter().enumerate().any(|(i, b)| i != *b) {
        bail!("the model's bodies are not in depth-first order");
    }

    out.push_str("MOTION\n");
    let _ = writeln!(out, "Frames: {}", frames.len());
    let _ = writeln!(out, "Frame Time: {:.9}", 1.0 / fps);
    let mut prev: Vec<Option<[f64; 3]>> = vec![None; nb];
    for p in frames {
        let pos = y_up(p.root_pos.map(|v| v as f64));
        for (i, v) in pos.iter().enumerate() {
            if i > 0 {
                out.push(' ');
            }
            num(&mut out, v * k, dec);
        }
        for (b, last) in prev.iter_mut().enumerate() {
            let q = if b == 0 {
                quat::mul(Z_UP_TO_Y_UP, unit(p.root_rot))
            } else {
                let e = &p.joint_rot[3 * (b - 1)..3 * b];
                quat::from_expmap([e[0] as f64, e[1] as f64, e[2] as f64])
            };
            let a = zxy_near(q, *last);
            *last = Some(a);
            for v in a {
                out.push(' ');
                num(&mut out, v.to_degrees(), 5);
            }
        }
        out.push('\n');
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn same_rotation(a: quat::Quat, b: quat::Quat) -> f64 {
        1.0 - quat::dot(a, b).abs()
    }

    #[test]
    fn euler_axes_follow_the_channel_order() {
        // Rz(90) alone turns x onto y
        let q = quat_from_zxy([PI / 2.0, 0.0, 0.0]);
        let v = quat::rotate(q, [1.0, 0.0, 0.0]);
        assert!((v[1] - 1.0).abs() < 1e-12, "{v:?}");
        // Rz then Rx (intrinsic): Rz(90) * Rx(90) takes y to z... applied
        // to column vectors: Rx(90) y = z, then Rz(90) z = z
        let q = quat_from_zxy([PI / 2.0, PI / 2.0, 0.0]);
        let v = quat::rotate(q, [0.0, 1.0, 0.0]);
        assert!((v[2] - 1.0).abs() < 1e-12, "{v:?}");
        let a = zxy_from_quat(quat_from_zxy([0.3, -0.4, 1.1]));
        for (x, y) in a.iter().zip([0.3, -0.4, 1.1]) {
            assert!((x - y).abs() < 1e-12, "{a:?}");
        }
    }

    #[test]
    fn y_up_is_the_rotation_c() {
        for v in [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.3, -2.0, 0.7],
        ] {
            let r = quat::rotate(Z_UP_TO_Y_UP, v);
            let c = y_up(v);
            for i in 0..3 {
                assert!((r[i] - c[i]).abs() < 1e-12, "{v:?}: {r:?} vs {c:?}");
            }
        }
    }

    #[test]
    fn gimbal_lock_still_gives_the_rotation() {
        for (z, y) in [(0.4, -1.0), (2.0, 0.5), (-3.0, 3.0)] {
            for x in [PI / 2.0, -PI / 2.0] {
                let q = quat_from_zxy([z, x, y]);
                let a = zxy_from_quat(q);
                assert!(same_rotation(quat_from_zxy(a), q) < 1e-12, "{a:?}");
                assert_eq!(a[2], 0.0);
            }
        }
    }

    proptest! {
        #[test]
        fn euler_round_trip(e in proptest::array::uniform3(-4.0f64..4.0), prev in proptest::array::uniform3(-9.0f64..9.0)) {
            let q = quat::from_expmap(e);
            let a = zxy_from_quat(q);
            prop_assert!(same_rotation(quat_from_zxy(a), q) < 1e-12);
            prop_assert!(a[1].abs() <= PI / 2.0 + 1e-12);
            let b = zxy_near(q, Some(prev));
            prop_assert!(same_rotation(quat_from_zxy(b), q) < 1e-12);
            // never farther from prev than the principal triple, unwrapped
            let d = |c: [f64; 3]| -> f64 { (0..3).map(|i| (unwrap(c[i], prev[i]) - prev[i]).powi(2)).sum() };
            let db: f64 = (0..3).map(|i| (b[i] - prev[i]).powi(2)).sum();
            prop_assert!(db <= d(a) + 1e-9);
        }
    }

    const TINY: &str = r#"<mujoco><worldbody>
        <body name="root" pos="0 0 1"><geom type="sphere" size="0.1"/>
          <body name="arm" pos="0.3 0 0"><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04"/>
            <body name="hand" pos="0.3 0 0"/></body>
          <body name="head" pos="0 0 0.4"><geom type="sphere" pos="0 0 0.1" size="0.1"/></body>
        </body></worldbody></mujoco>"#;

    fn track(frames: Vec<Option<Posture>>) -> Track {
        Track {
            name: "reference".into(),
            frames,
            masked: Vec::new(),
            value: None,
        }
    }

    #[test]
    fn hierarchy_offsets_and_frames_of_a_small_model() {
        let model = Model::parse(TINY).unwrap();
        let p = Posture {
            root_pos: [0.1, 0.2, 0.9],
            root_rot: [0.0, 0.0, 0.0, 1.0],
            joint_rot: [0.0, 0.0, std::f32::consts::FRAC_PI_2]
                .into_iter()
                .chain([0.0; 6])
                .collect(),
            ..Default::default()
        };
        let text = to_bvh(
            &model,
            &track(vec![None, Some(p), None]),
            50.0,
            Units::Metres,
        )
        .unwrap();
        let want = "HIERARCHY\nROOT root\n{\n\tOFFSET 0.000000 0.000000 0.000000\n\
            \tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n\
            \tJOINT arm\n\t{\n\t\tOFFSET 0.300000 0.000000 0.000000\n\
            \t\tCHANNELS 3 Zrotation Xrotation Yrotation\n\
            \t\tJOINT hand\n\t\t{\n\t\t\tOFFSET 0.300000 0.000000 0.000000\n\
            \t\t\tCHANNELS 3 Zrotation Xrotation Yrotation\n\
            \t\t\tEnd Site\n\t\t\t{\n\t\t\t\tOFFSET 0.150000 0.000000 0.000000\n\t\t\t}\n\
            \t\t}\n\t}\n\
            \tJOINT head\n\t{\n\t\tOFFSET 0.000000 0.000000 0.400000\n\
            \t\tCHANNELS 3 Zrotation Xrotation Yrotation\n\
            \t\tEnd Site\n\t\t{\n\t\t\tOFFSET 0.000000 0.000000 0.100000\n\t\t}\n\
            \t}\n}\nMOTION\nFrames: 3\nFrame Time: 0.020000000\n";
        assert!(text.starts_with(want), "{text}");
        // y up: (0.1, 0.2, 0.9) -> (0.1, 0.9, -0.2); the root's identity in
        // the simulator is C = -90 degrees about x; the arm turns 90 about z
        let line = "0.100000 0.900000 -0.200000 0.00000 -90.00000 0.00000 90.00000 0.00000 0.00000 0.00000 0.00000 0.00000 0.00000 0.00000 0.00000\n";
        assert_eq!(text[want.len()..], line.repeat(3));
        let cm = to_bvh(
            &model,
            &track(vec![Some(Posture {
                joint_rot: vec![0.0; 9],
                ..Default::default()
            })]),
            60.0,
            Units::Centimetres,
        )
        .unwrap();
        assert!(
            cm.contains("\t\tOFFSET 30.0000 0.0000 0.0000\n")
                && cm.contains("Frame Time: 0.016666667\n")
        );
    }

    #[test]
    fn refuses_tracks_it_cannot_write() {
        let model = Model::parse(TINY).unwrap();
        let e = to_bvh(&model, &track(vec![None]), 30.0, Units::Metres).unwrap_err();
        assert!(e.to_string().contains("no valid frame"), "{e}");
        let p = Posture {
            joint_rot: vec![0.0; 6],
            ..Default::default()
        };
        let e = to_bvh(&model, &track(vec![Some(p)]), 30.0, Units::Metres).unwrap_err();
        assert!(
            e.to_string()
                .contains("6 joint values for a model of 4 bodies"),
            "{e}"
        );
        let p = Posture {
            joint_rot: vec![f32::NAN; 9],
            ..Default::default()
        };
        let e = to_bvh(&model, &track(vec![Some(p.clone())]), 30.0, Units::Metres).unwrap_err();
        assert!(e.to_string().contains("not finite"), "{e}");
        let e = to_bvh(&model, &track(vec![Some(p)]), 0.0, Units::Metres).unwrap_err();
        assert!(e.to_string().contains("frame rate"), "{e}");
    }

    #[test]
    fn continuous_curves_pass_through_the_middle_angle_limit() {
        // a knee bending about x from 0 to 150 degrees
        let mut prev = None;
        for i in 0..=150 {
            let t = (i as f64).to_radians();
            let a = zxy_near(quat_from_zxy([0.0, t, 0.0]), prev);
            assert!(
                (a[1] - t).abs() < 1e-9 && a[0].abs() < 1e-9 && a[2].abs() < 1e-9,
                "{i}: {a:?}"
            );
            prev = Some(a);
        }
        // a heading turning through +-180
        let mut prev = None;
        for i in 0..=720 {
            let t = (i as f64).to_radians();
            let a = zxy_near(quat_from_zxy([0.0, 0.0, t]), prev);
            assert!((a[2] - t).abs() < 1e-9, "{i}: {a:?}");
            prev = Some(a);
        }
    }
}
