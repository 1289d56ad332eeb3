//! The motion viewer: one self-contained HTML page that plays back the
//! humanoid (the capsules, spheres, boxes and cylinders of its MJCF model)
//! with its ball or objects.
//!
//! A page holds a [`Scene`]: the model's geoms in their body frames, each
//! object's triangle mesh (from its simulated collision shape, so the page
//! shows what the physics touches), and a list of [`Item`]s, each with one or
//! more [`Actor`]s played side by side in split views on one clock (a
//! rollout beside its reference). Body poses come from exp-map forward
//! kinematics of the MJCF ([`crate::sim::mjcf::body_poses`]), the same
//! kinematics the simulation uses, so any state the project stores (an
//! ingested frame, an STF start, a recorded rollout step) can be drawn.
//!
//! The renderer is our own small WebGL 1 program (`assets/viewer.js`, about
//! 400 lines: per-geom meshes, one Lambert shader, a checkered ground, blob
//! shadows, an orbit camera) rather than a bundled 3-D library: the scene
//! needs nothing more, and the page stays a few hundred kilobytes plus its
//! data, with no network needed to open it. Frame data travel as base64
//! little-endian `f32` arrays.

use crate::motion::state::Posture;
use crate::sim::mjcf::{body_poses, Model};
use crate::sim::objects::ObjectSpec;
use anyhow::{bail, Context, Result};
use rapier3d::math::{Pose, Vector};
use rapier3d::prelude::SharedShape;
use serde::Serialize;
use std::path::Path;

const TEMPLATE: &str = include_str!("../assets/viewer.html");
const SCRIPT: &str = include_str!("../assets/viewer.js");

/// One geom in its body's frame.
#[derive(Clone, Debug, Serialize)]
pub struct GeomView {
    /// `capsule`, `sphere`, `box` or `cylinder`.
    pub kind: &'static str,
    /// capsule / cylinder: (radius, half length, 0); sphere: (radius, 0, 0);
    /// box: half extents.
    pub size: [f32; 3],
    /// Centre in the body frame, m.
    pub pos: [f32; 3],
    /// Rotation in the body frame (x, y, z, w); capsules and cylinders lie
    /// along the rotated z axis.
    pub quat: [f32; 4],
}

/// One body: its name and geoms.
#[derive(Clone, Debug, Serialize)]
pub struct BodyView {
    /// Body name.
    pub name: String,
    /// Geoms.
    pub geoms: Vec<GeomView>,
}

/// One object's triangle mesh in its own frame.
#[derive(Clone, Debug, Serialize)]
pub struct ObjectView {
    /// Object name (`ball`, `kettle`, ...).
    pub name: String,
    /// Vertex positions, `[V*3]`, base64 `f32`.
    pub verts: String,
    /// Triangles, `[T*3]` vertex indices.
    pub tris: Vec<u32>,
}

/// One moving figure: the humanoid and its objects over time.
#[derive(Clone, Debug, Serialize)]
pub struct Actor {
    /// Label over its view (`reference`, `rollout`, ...).
    pub name: String,
    /// Number of frames.
    pub frames: usize,
    /// Per frame and body: position (3) then rotation (x, y, z, w), base64 `f32`.
    pub body: String,
    /// Per frame and object: position (3) then rotation, base64 `f32`.
    pub obj: String,
    /// Per frame: 1 where the frame is masked (no reward target, or a missing
    /// frame held at the last valid pose).
    pub masked: Vec<u8>,
    /// Per frame: a number shown beside the frame counter (the step's SM
    /// reward in a rollout; NaN: none), base64 `f32`; empty: none.
    pub value: String,
    /// Name of that number.
    pub value_name: String,
}

/// One selectable entry of the page.
#[derive(Clone, Debug, Serialize)]
pub struct Item {
    /// Title in the selector.
    pub title: String,
    /// Skill label shown in the corner.
    pub skill: String,
    /// One line of details.
    pub note: String,
    /// Frames per second of playback at speed 1.
    pub fps: f64,
    /// The item's objects, in state order, as indices into [`Scene::objects`].
    pub objects: Vec<usize>,
    /// Figures drawn side by side.
    pub actors: Vec<Actor>,
}

/// Everything a page shows.
#[derive(Clone, Debug, Serialize)]
pub struct Scene {
    /// Page title.
    pub title: String,
    /// The humanoid's bodies in model order.
    pub bodies: Vec<BodyView>,
    /// Object meshes the items refer to.
    pub objects: Vec<ObjectView>,
    /// The entries.
    pub items: Vec<Item>,
}

fn b64_f32(v: &[f32]) -> String {
    let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    base64_encode(&bytes)
}

/// Standard base64 with padding. Written here because it is twenty lines and
/// the page is the only place the project needs it.
pub fn base64_encode(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        s.push(A[(n >> 18) as usize & 63] as char);
        s.push(A[(n >> 12) as usize & 63] as char);
        s.push(if c.len() > 1 {
            A[(n >> 6) as usize & 63] as char
        } else {
            '='
        });
        s.push(if c.len() > 2 {
            A[n as usize & 63] as char
        } else {
            '='
        });
    }
    s
}

/// Rotation (x, y, z, w) taking +z to the unit vector `d`.
fn z_to(d: [f64; 3]) -> [f32; 4] {
    // half-way quaternion between z and d
    let (x, y, z) = (-d[1], d[0], 0.0);
    let w = 1.0 + d[2];
    if w < 1e-9 {
        return [1.0, 0.0, 0.0, 0.0]; // d = -z: half turn about x
    }
    crate::motion::quat::normalize([x, y, z, w]).map(|v| v as f32)
}

fn geom_view(g: &crate::sim::mjcf::Geom, body: &str) -> Result<GeomView> {
    let r = *g.size.first().unwrap_or(&0.0) as f32;
    let quat = match g.quat {
        Some([w, x, y, z]) => {
            let n = (w * w + x * x + y * y + z * z).sqrt().max(1e-12);
            [
                (x / n) as f32,
                (y / n) as f32,
                (z / n) as f32,
                (w / n) as f32,
            ]
        }
        None => [0.0, 0.0, 0.0, 1.0],
    };
    let pos = g.pos.map(|v| v as f32);
    Ok(match g.kind.as_str() {
        "capsule" | "cylinder" => {
            let Some(ft) = g.fromto else {
                bail!(
                    "body `{body}`: a {} without `fromto` cannot be drawn",
                    g.kind
                );
            };
            let d = [ft[3] - ft[0], ft[4] - ft[1], ft[5] - ft[2]];
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let centre = [
                0.5 * (ft[0] + ft[3]) as f32,
                0.5 * (ft[1] + ft[4]) as f32,
                0.5 * (ft[2] + ft[5]) as f32,
            ];
            let quat = if len > 1e-9 {
                z_to([d[0] / len, d[1] / len, d[2] / len])
            } else {
                [0.0, 0.0, 0.0, 1.0]
            };
            GeomView {
                kind: if g.kind == "capsule" {
                    "capsule"
                } else {
                    "cylinder"
                },
                size: [r, 0.5 * len as f32, 0.0],
                pos: centre,
                quat,
            }
        }
        "sphere" => GeomView {
            kind: "sphere",
            size: [r, 0.0, 0.0],
            pos,
            quat,
        },
        "box" => {
            if g.size.len() != 3 {
                bail!("body `{body}`: a box needs three half-sizes");
            }
            GeomView {
                kind: "box",
                size: [g.size[0] as f32, g.size[1] as f32, g.size[2] as f32].map(f32::abs),
                pos,
                quat,
            }
        }
        other => bail!("body `{body}`: geom type `{other}` cannot be drawn"),
    })
}

/// The model's geoms per body.
pub fn bodies(model: &Model) -> Result<Vec<BodyView>> {
    model
        .bodies
        .iter()
        .map(|b| {
            Ok(BodyView {
                name: b.name.clone(),
                geoms: b
                    .geoms
                    .iter()
                    .map(|g| geom_view(g, &b.name))
                    .collect::<Result<_>>()?,
            })
        })
        .collect()
}

/// Append the triangles of `shape` placed at `pose` to `verts` / `tris`
/// (`[V*3]` positions in the frame of `pose`, m; `[T*3]` vertex indices,
/// counter-clockwise seen from outside). Shared with the glTF export.
pub(crate) fn shape_mesh(
    shape: &SharedShape,
    pose: Pose,
    verts: &mut Vec<f32>,
    tris: &mut Vec<u32>,
) {
    let (v, t): (Vec<Vector>, Vec<[u32; 3]>) = if let Some(c) = shape.as_compound() {
        for (p, s) in c.shapes() {
            shape_mesh(s, pose * *p, verts, tris);
        }
        return;
    } else if let Some(b) = shape.as_ball() {
        b.to_trimesh(24, 12)
    } else if let Some(b) = shape.as_cuboid() {
        b.to_trimesh()
    } else if let Some(c) = shape.as_capsule() {
        c.to_trimesh(16, 8)
    } else if let Some(c) = shape.as_cylinder() {
        c.to_trimesh(24)
    } else if let Some(c) = shape.as_convex_polyhedron() {
        c.to_trimesh()
    } else {
        return;
    };
    let base = (verts.len() / 3) as u32;
    for p in v {
        let q = pose.transform_point(p);
        verts.extend_from_slice(&[q.x, q.y, q.z]);
    }
    for tri in t {
        tris.extend(tri.iter().map(|i| i + base));
    }
}

/// An object's drawable mesh: the triangles of its collision shape.
pub fn object_view(spec: &ObjectSpec) -> ObjectView {
    let (mut v, mut t) = (Vec::new(), Vec::new());
    shape_mesh(&spec.shape, Pose::IDENTITY, &mut v, &mut t);
    ObjectView {
        name: spec.name.clone(),
        verts: b64_f32(&v),
        tris: t,
    }
}

/// A figure from per-frame postures (`None`: a missing frame, drawn at the
/// last valid posture and marked masked). `masked` marks further frames;
/// `value` is one number per frame shown beside the counter.
pub fn actor(
    name: &str,
    model: &Model,
    n_objects: usize,
    frames: &[Option<Posture>],
    masked: &[bool],
    value: Option<(&str, &[f32])>,
) -> Result<Actor> {
    let nb = model.bodies.len();
    let first = frames
        .iter()
        .flatten()
        .next()
        .with_context(|| format!("`{name}` has no valid frame to draw"))?;
    let mut last = first;
    let mut body = Vec::with_capacity(frames.len() * nb * 7);
    let mut obj = Vec::with_capacity(frames.len() * n_objects * 7);
    let mut mask = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        if let Some(p) = f {
            if p.joint_rot.len() != 3 * (nb - 1) {
                bail!(
                    "`{name}` frame {i}: {} joint values for a model of {} joints",
                    p.joint_rot.len(),
                    nb - 1
                );
            }
            last = p;
        }
        let (pos, rot) = body_poses(model, last.root_pos, last.root_rot, &last.joint_rot);
        for b in 0..nb {
            body.extend_from_slice(&pos[3 * b..3 * b + 3]);
            body.extend_from_slice(&rot[4 * b..4 * b + 4]);
        }
        for k in 0..n_objects {
            match (
                last.obj_pos.get(3 * k..3 * k + 3),
                last.obj_rot.get(4 * k..4 * k + 4),
            ) {
                (Some(p), Some(q)) => {
                    obj.extend_from_slice(p);
                    obj.extend_from_slice(q);
                }
                _ => obj.extend_from_slice(&[0.0, 0.0, -10.0, 0.0, 0.0, 0.0, 1.0]),
            }
        }
        mask.push((f.is_none() || masked.get(i).copied().unwrap_or(false)) as u8);
    }
    let (value, value_name) = match value {
        Some((n, v)) => {
            if v.len() != frames.len() {
                bail!("`{name}`: {} values for {} frames", v.len(), frames.len());
            }
            (b64_f32(v), n.to_string())
        }
        None => (String::new(), String::new()),
    };
    Ok(Actor {
        name: name.to_string(),
        frames: frames.len(),
        body: b64_f32(&body),
        obj: b64_f32(&obj),
        masked: mask,
        value,
        value_name,
    })
}

/// The page for `scene`: the template with the script and the scene's JSON
/// inlined (`</` escaped so no string can close the script element).
pub fn html(scene: &Scene) -> Result<String> {
    let json = serde_json::to_string(scene)?.replace("</", "<\\/");
    let title = scene
        .title
        .replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;");
    Ok(TEMPLATE
        .replace("__TITLE__", &title)
        .replace("__SCRIPT__", SCRIPT)
        .replace("__SCENE__", &json))
}

/// Write the page to `path` (staged in a temporary file, then renamed).
pub fn write(scene: &Scene, path: &Path) -> Result<()> {
    if scene.items.is_empty() {
        bail!("nothing to show: the page would have no item");
    }
    for it in &scene.items {
        if let Some(k) = it.objects.iter().find(|k| **k >= scene.objects.len()) {
            bail!(
                "item `{}` names object mesh {k} of {}",
                it.title,
                scene.objects.len()
            );
        }
    }
    let text = html(scene)?;
    if let Some(dir) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let mut staged = crate::table::io::Staged::new();
    staged.text(path, &text)?;
    staged.commit()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_known_encodings() {
        assert_eq!(base64_encode(b""), "");
        assert_eq!(base64_encode(b"f"), "Zg==");
        assert_eq!(base64_encode(b"fo"), "Zm8=");
        assert_eq!(base64_encode(b"foo"), "Zm9v");
        assert_eq!(base64_encode(b"foobar"), "Zm9vYmFy");
        assert_eq!(base64_encode(&[0xff, 0xfe, 0x00]), "//4A");
    }

    #[test]
    fn z_to_rotates_z_onto_the_direction() {
        use crate::motion::quat;
        for d in [
            [1.0, 0.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [0.6, 0.0, 0.8],
        ] {
            let q = z_to(d).map(|v| v as f64);
            let r = quat::rotate(q, [0.0, 0.0, 1.0]);
            for k in 0..3 {
                assert!((r[k] - d[k]).abs() < 1e-6, "{d:?} -> {r:?}");
            }
        }
    }

    #[test]
    fn script_text_cannot_close_the_page_early() {
        let scene = Scene {
            title: "a </script> <b>".into(),
            bodies: vec![],
            objects: vec![],
            items: vec![Item {
                title: "</script><script>alert(1)</script>".into(),
                skill: "x".into(),
                note: String::new(),
                fps: 60.0,
                objects: vec![],
                actors: vec![],
            }],
        };
        let page = html(&scene).unwrap();
        let data = page.split("id=\"scene\"").nth(1).unwrap();
        let end = data.find("</script>").unwrap();
        assert!(data[..end].contains("<\\/script>"));
        assert!(page.contains("<title>skillaug: a &lt;/script&gt; &lt;b&gt;</title>"));
    }
}
