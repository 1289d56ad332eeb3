//! glTF 2.0 binary export: motions as one `.glb` file with the humanoid,
//! its objects and one animation per motion.
//!
//! # Document (glTF 2.0 specification, Khronos, version 2.0.1)
//! * One scene. Per character (as many as the motion with the most tracks
//!   has: a rollout and its reference make two) a node `character K:
//!   ROLES` (the track names it plays, `character 1: reference`) holding
//!   a node tree of the MJCF humanoid (§3.5.2 Nodes and hierarchy):
//!   one node per body, nested like the model, named after the body
//!   (`Pelvis`; characters after the first add `.K`), its `translation` the
//!   body's offset in its parent's frame (MJCF `pos`), its `rotation`
//!   animated. The root body's node is animated in translation and
//!   rotation. Each character's objects (ball, kettle, cup, ...) are nodes
//!   beside its root body, animated in translation and rotation.
//! * Character K (from 0) stands `1.5 * K` m along +x from the first, so a
//!   rollout and its reference play side by side rather than overlaid.
//! * Meshes (§3.7.2): a body's geoms (capsules, spheres, boxes, cylinders) as
//!   one triangle primitive in the body's frame; an object's collision shape
//!   (what the simulation touches) in its own frame. The triangles come
//!   from the viewer's mesh code ([`crate::view::bodies`],
//!   `crate::view::shape_mesh`); normals are averaged over faces within
//!   40 degrees of each other, so curved surfaces shade smoothly and box
//!   edges stay sharp. `POSITION` (with min/max) and `NORMAL` attributes,
//!   `u16` indices (`u32` for meshes of 65535 vertices or more), two
//!   materials (humanoid, objects). Meshes are shared by the characters.
//! * Animations (§3.11): one per motion, named after its title. The
//!   translation and rotation samplers are `LINEAR` with one key per frame (input: times `i / fps`, s,
//!   with min/max), outputs `VEC3` translations (m) and `VEC4` rotations
//!   (unit quaternions, x, y, z, w, each the one of `q` and `-q` nearer the
//!   previous key, so interpolation takes the short way). Missing frames hold
//!   the last valid posture. All animations target the same nodes; a
//!   character or object a motion does not have is hidden by a one-key
//!   `STEP` scale of 0 (and shown by a scale of 1 in the motions that have
//!   it), written only when some motion lacks one.
//! * Binary container (§4.4 GLB file format): 12-byte header (`glTF`,
//!   version 2, total length), a JSON chunk padded with spaces and a BIN
//!   chunk padded with zeros, each to 4 bytes; every buffer view starts on a
//!   4-byte boundary in the single buffer.
//!
//! # Axes and units (§3.4 Coordinate system and units)
//! glTF is y up, metres, right-handed. The simulator's world is z up, so
//! world quantities go through the rotation `C` of -90 degrees about x,
//! `(x, y, z) -> (x, z, -y)` (the BVH export's [`super::bvh::y_up`]): a root
//! or object position `p` becomes `C p`, a root or object rotation `R`
//! becomes `C R`. Body offsets, joint rotations and meshes are in body (or
//! object) frames and are kept as they are. Each body's world pose in the
//! file is then exactly `C` times its simulator pose (plus the character's
//! offset along x).
//!
//! The JSON document is built with the `gltf-json` crate (the `gltf`
//! project's serde model of the schema) and checked with its validation
//! before it is written; the GLB container is written here.

use super::bvh::{held, unit, y_up, Z_UP_TO_Y_UP};
use super::motions::Motion;
use crate::motion::quat;
use crate::sim::mjcf::Model;
use crate::sim::ObjectSpec;
use crate::view::{shape_mesh, GeomView};
use anyhow::{bail, Context, Result};
use gltf_json as json;
use json::validation::{Checked::Valid, USize64};
use json::Index;
use rapier3d::math::{Pose, Rotation, Vector};
use rapier3d::prelude::SharedShape;
use std::collections::HashMap;

/// Distance between the characters of a motion with several tracks, m
/// (along +x).
pub const CHARACTER_SPACING: f32 = 1.5;

/// Faces meeting at a vertex within this angle share its normal, degrees.
const CREASE_DEG: f64 = 40.0;

/// A triangle mesh with per-vertex normals.
#[derive(Default)]
struct MeshData {
    /// `[V]` positions, m.
    pos: Vec<[f32; 3]>,
    /// `[V]` unit normals.
    nrm: Vec<[f32; 3]>,
    /// `[T*3]` indices, counter-clockwise seen from outside.
    idx: Vec<u32>,
}

impl MeshData {
    /// Append the triangles `verts` (`[V*3]`) / `tris` (`[T*3]`) with
    /// normals shared across faces within [`CREASE_DEG`] of each other;
    /// degenerate triangles are dropped.
    fn add(&mut self, verts: &[f32], tris: &[u32]) {
        // weld identical positions (a shape's seams may repeat them)
        let mut weld: HashMap<[u32; 3], u32> = HashMap::new();
        let mut wpos: Vec<[f64; 3]> = Vec::new();
        let mut map = Vec::with_capacity(verts.len() / 3);
        for v in verts.chunks_exact(3) {
            let key = [v[0].to_bits(), v[1].to_bits(), v[2].to_bits()];
            let id = *weld.entry(key).or_insert_with(|| {
                wpos.push([v[0] as f64, v[1] as f64, v[2] as f64]);
                (wpos.len() - 1) as u32
            });
            map.push(id);
        }
        let mut faces: Vec<([u32; 3], [f64; 3])> = Vec::new();
        for t in tris.chunks_exact(3) {
            let f = [map[t[0] as usize], map[t[1] as usize], map[t[2] as usize]];
            let [a, b, c] = f.map(|i| wpos[i as usize]);
            let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let w = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let n = [
                u[1] * w[2] - u[2] * w[1],
                u[2] * w[0] - u[0] * w[2],
                u[0] * w[1] - u[1] * w[0],
            ];
            if quat::norm(n) > 1e-12 {
                faces.push((f, n));
            }
        }
        let mut incident: Vec<Vec<usize>> = vec![Vec::new(); wpos.len()];
        for (k, (f, _)) in faces.iter().enumerate() {
            for &v in f {
                incident[v as usize].push(k);
            }
        }
        let unit_n = |n: [f64; 3]| {
            let l = quat::norm(n);
            n.map(|x| x / l)
        };
        let crease = CREASE_DEG.to_radians().cos();
        let mut out: HashMap<(u32, [u32; 3]), u32> = HashMap::new();
        for (f, n) in &faces {
            let nf = unit_n(*n);
            for &v in f {
                let mut s = [0.0; 3];
                for &g in &incident[v as usize] {
                    let ng = faces[g].1;
                    let u = unit_n(ng);
                    if nf[0] * u[0] + nf[1] * u[1] + nf[2] * u[2] >= crease {
                        // area-weighted
                        s = [s[0] + ng[0], s[1] + ng[1], s[2] + ng[2]];
                    }
                }
                let nv = unit_n(s).map(|x| x as f32);
                let key = (v, nv.map(f32::to_bits));
                let id = *out.entry(key).or_insert_with(|| {
                    self.pos.push(wpos[v as usize].map(|x| x as f32));
                    self.nrm.push(nv);
                    (self.pos.len() - 1) as u32
                });
                self.idx.push(id);
            }
        }
    }
}

/// The rapier shape of a viewer geom and its pose in the body frame.
fn geom_shape(g: &GeomView) -> Result<(SharedShape, Pose)> {
    let [x, y, z, w] = g.quat;
    let pose = Pose::from_parts(
        Vector::new(g.pos[0], g.pos[1], g.pos[2]),
        Rotation::from_xyzw(x, y, z, w).normalize(),
    );
    let [a, b, c] = g.size;
    Ok(match g.kind {
        "capsule" => (SharedShape::capsule_z(b, a), pose),
        // parry's cylinder lies along y; the geom's along z: turn y onto z
        "cylinder" => (
            SharedShape::cylinder(b, a),
            pose * Pose::from_rotation(Rotation::from_rotation_x(std::f32::consts::FRAC_PI_2)),
        ),
        "sphere" => (SharedShape::ball(a), pose),
        "box" => (SharedShape::cuboid(a, b, c), pose),
        other => bail!("geom type `{other}` has no mesh"),
    })
}

/// The mesh of every body of `model` (`None` for a body without geoms), in
/// the body's frame.
fn body_meshes(model: &Model) -> Result<Vec<Option<MeshData>>> {
    crate::view::bodies(model)?
        .iter()
        .map(|b| {
            if b.geoms.is_empty() {
                return Ok(None);
            }
            let mut m = MeshData::default();
            for g in &b.geoms {
                let (shape, pose) = geom_shape(g).with_context(|| format!("body `{}`", b.name))?;
                let (mut v, mut t) = (Vec::new(), Vec::new());
                shape_mesh(&shape, pose, &mut v, &mut t);
                m.add(&v, &t);
            }
            Ok((!m.idx.is_empty()).then_some(m))
        })
        .collect()
}

/// An object's mesh in its own frame (`None`: a shape with no triangles).
fn object_mesh(spec: &ObjectSpec) -> Option<MeshData> {
    let (mut v, mut t) = (Vec::new(), Vec::new());
    shape_mesh(&spec.shape, Pose::IDENTITY, &mut v, &mut t);
    let mut m = MeshData::default();
    m.add(&v, &t);
    (!m.idx.is_empty()).then_some(m)
}

/// The document under construction and its binary buffer.
struct Doc {
    root: json::Root,
    bin: Vec<u8>,
}

fn empty_node(name: String) -> json::Node {
    json::Node {
        camera: None,
        children: None,
        extensions: None,
        extras: Default::default(),
        matrix: None,
        mesh: None,
        name: Some(name),
        rotation: None,
        scale: None,
        translation: None,
        skin: None,
        weights: None,
    }
}

impl Doc {
    /// A buffer view over `bytes` (appended on a 4-byte boundary).
    fn view(
        &mut self,
        bytes: &[u8],
        target: Option<json::buffer::Target>,
    ) -> Index<json::buffer::View> {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.root.push(json::buffer::View {
            buffer: Index::new(0),
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            name: None,
            target: target.map(Valid),
            extensions: None,
            extras: Default::default(),
        })
    }

    /// An accessor of `f32` vectors of `width` components (`data.len()` a
    /// multiple of it), in a view of its own; with per-component min/max
    /// when `bounds`.
    fn floats(
        &mut self,
        data: &[f32],
        width: usize,
        bounds: bool,
        target: Option<json::buffer::Target>,
    ) -> Index<json::Accessor> {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes, target);
        let (min, max) = if bounds {
            let mut lo = vec![f32::INFINITY; width];
            let mut hi = vec![f32::NEG_INFINITY; width];
            for row in data.chunks_exact(width) {
                for (k, v) in row.iter().enumerate() {
                    lo[k] = lo[k].min(*v);
                    hi[k] = hi[k].max(*v);
                }
            }
            (Some(json::Value::from(lo)), Some(json::Value::from(hi)))
        } else {
            (None, None)
        };
        let type_ = match width {
            1 => json::accessor::Type::Scalar,
            2 => json::accessor::Type::Vec2,
            3 => json::accessor::Type::Vec3,
            _ => json::accessor::Type::Vec4,
        };
        self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: Some(USize64(0)),
            count: USize64::from(data.len() / width),
            component_type: Valid(json::accessor::GenericComponentType(
                json::accessor::ComponentType::F32,
            )),
            extensions: None,
            extras: Default::default(),
            type_: Valid(type_),
            min,
            max,
            name: None,
            normalized: false,
            sparse: None,
        })
    }

    /// A mesh of one triangle primitive.
    fn mesh(
        &mut self,
        m: &MeshData,
        name: &str,
        material: Index<json::Material>,
    ) -> Index<json::Mesh> {
        use json::buffer::Target::{ArrayBuffer, ElementArrayBuffer};
        let pos: Vec<f32> = m.pos.iter().flatten().copied().collect();
        let nrm: Vec<f32> = m.nrm.iter().flatten().copied().collect();
        let p = self.floats(&pos, 3, true, Some(ArrayBuffer));
        let n = self.floats(&nrm, 3, false, Some(ArrayBuffer));
        // u16 where every index fits below its restart value 65535 (glTF 2.0 §3.7.2.1)
        let (bytes, component) = if m.pos.len() < 65535 {
            let b: Vec<u8> = m
                .idx
                .iter()
                .flat_map(|v| (*v as u16).to_le_bytes())
                .collect();
            (b, json::accessor::ComponentType::U16)
        } else {
            let b: Vec<u8> = m.idx.iter().flat_map(|v| v.to_le_bytes()).collect();
            (b, json::accessor::ComponentType::U32)
        };
        let view = self.view(&bytes, Some(ElementArrayBuffer));
        let idx = self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: Some(USize64(0)),
            count: USize64::from(m.idx.len()),
            component_type: Valid(json::accessor::GenericComponentType(component)),
            extensions: None,
            extras: Default::default(),
            type_: Valid(json::accessor::Type::Scalar),
            min: None,
            max: None,
            name: None,
            normalized: false,
            sparse: None,
        });
        let mut attributes = std::collections::BTreeMap::new();
        attributes.insert(Valid(json::mesh::Semantic::Positions), p);
        attributes.insert(Valid(json::mesh::Semantic::Normals), n);
        self.root.push(json::Mesh {
            extensions: None,
            extras: Default::default(),
            name: Some(name.to_string()),
            primitives: vec![json::mesh::Primitive {
                attributes,
                extensions: None,
                extras: Default::default(),
                indices: Some(idx),
                material: Some(material),
                mode: Valid(json::mesh::Mode::Triangles),
                targets: None,
            }],
            weights: None,
        })
    }

    fn material(&mut self, name: &str, rgb: [f32; 3]) -> Index<json::Material> {
        let mut m = json::Material {
            name: Some(name.to_string()),
            ..Default::default()
        };
        m.pbr_metallic_roughness.base_color_factor =
            json::material::PbrBaseColorFactor([rgb[0], rgb[1], rgb[2], 1.0]);
        m.pbr_metallic_roughness.metallic_factor = json::material::StrengthFactor(0.0);
        m.pbr_metallic_roughness.roughness_factor = json::material::StrengthFactor(0.7);
        self.root.push(m)
    }
}

/// One character's nodes.
struct Character {
    /// The `character K` node.
    top: Index<json::Node>,
    /// Per body, in model order.
    bodies: Vec<Index<json::Node>>,
    /// Per object of the `objects` argument.
    objects: Vec<Index<json::Node>>,
}

/// An animation under construction.
struct Anim {
    channels: Vec<json::animation::Channel>,
    samplers: Vec<json::animation::Sampler>,
}

impl Anim {
    fn add(
        &mut self,
        node: Index<json::Node>,
        path: json::animation::Property,
        input: Index<json::Accessor>,
        output: Index<json::Accessor>,
        interpolation: json::animation::Interpolation,
    ) {
        let sampler = Index::new(self.samplers.len() as u32);
        self.samplers.push(json::animation::Sampler {
            extensions: None,
            extras: Default::default(),
            input,
            interpolation: Valid(interpolation),
            output,
        });
        self.channels.push(json::animation::Channel {
            sampler,
            target: json::animation::Target {
                extensions: None,
                extras: Default::default(),
                node,
                path: Valid(path),
            },
            extensions: None,
            extras: Default::default(),
        });
    }
}

/// Quaternions `[N]` as f32 `[N*4]`, each unit and the one of `q`, `-q`
/// nearer the previous.
fn rotation_keys(qs: impl Iterator<Item = quat::Quat>) -> Vec<f32> {
    let mut prev: Option<quat::Quat> = None;
    let mut out = Vec::new();
    for q in qs {
        let mut q = quat::normalize(q);
        if let Some(p) = prev {
            q = quat::sign_like(q, p);
        }
        prev = Some(q);
        out.extend(q.map(|v| v as f32));
    }
    out
}

/// The GLB container of a JSON document and its binary buffer (glTF 2.0
/// §4.4): header, JSON chunk padded with spaces, BIN chunk padded with zeros.
///
/// # Errors
/// A file over 4 GiB (the header's 32-bit length).
pub fn glb_container(json: &[u8], bin: &[u8]) -> Result<Vec<u8>> {
    let pad = |n: usize| (4 - n % 4) % 4;
    let json_len = json.len() + pad(json.len());
    let bin_len = bin.len() + pad(bin.len());
    let total = 12 + 8 + json_len + if bin.is_empty() { 0 } else { 8 + bin_len };
    let Ok(total32) = u32::try_from(total) else {
        bail!("the glTF binary would be {total} bytes, over the format's 4 GiB limit");
    };
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&total32.to_le_bytes());
    out.extend_from_slice(&(json_len as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(json);
    out.resize(out.len() + pad(json.len()), b' ');
    if !bin.is_empty() {
        out.extend_from_slice(&(bin_len as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(bin);
        out.resize(out.len() + pad(bin.len()), 0);
    }
    debug_assert_eq!(out.len(), total);
    Ok(out)
}

/// The `.glb` bytes of `motions`: one animation each (module doc for the
/// layout, axes and units). `objects` are the shapes of every object the
/// motions name (matched by [`ObjectSpec::name`]); `model` is the humanoid
/// of every track.
///
/// # Errors
/// No motion; a motion without tracks, with a non-positive frame rate, or
/// naming an object `objects` lacks; a track without a valid frame or with
/// postures of another model; a model geom with no mesh (`view::bodies`).
pub fn to_glb(model: &Model, objects: &[ObjectSpec], motions: &[Motion]) -> Result<Vec<u8>> {
    if motions.is_empty() {
        bail!("no motion to export");
    }
    let nb = model.bodies.len();
    if nb == 0 || model.bodies[0].parent.is_some() {
        bail!("the model has no root body first");
    }
    for (i, b) in model.bodies.iter().enumerate().skip(1) {
        if b.parent.is_none_or(|p| p >= i) {
            bail!("body `{}` does not follow its parent", b.name);
        }
    }
    // each motion's object slots as indices into `objects`
    let mut slots: Vec<Vec<usize>> = Vec::with_capacity(motions.len());
    for m in motions {
        if m.tracks.is_empty() {
            bail!("{}: no track to export", m.title);
        }
        if !(m.fps.is_finite() && m.fps > 0.0) {
            bail!("{}: frame rate {} is not a positive number", m.title, m.fps);
        }
        slots.push(
            m.objects
                .iter()
                .map(|n| {
                    objects
                        .iter()
                        .position(|o| &o.name == n)
                        .with_context(|| format!("{}: no shape given for object `{n}`", m.title))
                })
                .collect::<Result<_>>()?,
        );
    }
    let n_chars = motions.iter().map(|m| m.tracks.len()).max().unwrap_or(1);

    let mut doc = Doc {
        root: json::Root {
            asset: json::Asset {
                generator: Some(format!("skillaug {}", env!("CARGO_PKG_VERSION"))),
                ..Default::default()
            },
            ..Default::default()
        },
        bin: Vec::new(),
    };
    let skin = doc.material("humanoid", [0.55, 0.62, 0.75]);
    // no object material without objects (the validator flags it unused)
    let thing = (!objects.is_empty()).then(|| doc.material("object", [0.9, 0.45, 0.15]));
    let body_mesh: Vec<Option<Index<json::Mesh>>> = body_meshes(model)?
        .iter()
        .zip(&model.bodies)
        .map(|(m, b)| m.as_ref().map(|m| doc.mesh(m, &b.name, skin)))
        .collect();
    let object_mesh: Vec<Option<Index<json::Mesh>>> = objects
        .iter()
        .map(|o| {
            object_mesh(o)
                .zip(thing)
                .map(|(m, t)| doc.mesh(&m, &o.name, t))
        })
        .collect();

    let mut chars = Vec::with_capacity(n_chars);
    for k in 0..n_chars {
        let suffix = if k == 0 {
            String::new()
        } else {
            format!(".{k}")
        };
        let first = doc.root.nodes.len() as u32;
        for (i, b) in model.bodies.iter().enumerate() {
            let mut n = empty_node(format!("{}{suffix}", b.name));
            n.mesh = body_mesh[i];
            if b.parent.is_some() {
                n.translation = Some(b.pos.map(|v| v as f32));
            }
            doc.root.push(n);
        }
        let bodies: Vec<Index<json::Node>> =
            (0..nb as u32).map(|i| Index::new(first + i)).collect();
        for (i, b) in model.bodies.iter().enumerate() {
            if let Some(p) = b.parent {
                let parent = &mut doc.root.nodes[bodies[p].value()];
                parent.children.get_or_insert_with(Vec::new).push(bodies[i]);
            }
        }
        let objs: Vec<Index<json::Node>> = objects
            .iter()
            .enumerate()
            .map(|(j, o)| {
                let mut n = empty_node(format!("{}{suffix}", o.name));
                n.mesh = object_mesh[j];
                doc.root.push(n)
            })
            .collect();
        // named after what it plays: "character 1: reference"
        let mut roles: Vec<&str> = Vec::new();
        for m in motions {
            if let Some(t) = m.tracks.get(k) {
                if !roles.contains(&t.name.as_str()) {
                    roles.push(&t.name);
                }
            }
        }
        let mut top = empty_node(format!("character {k}: {}", roles.join(" / ")));
        if k > 0 {
            top.translation = Some([CHARACTER_SPACING * k as f32, 0.0, 0.0]);
        }
        top.children = Some(
            std::iter::once(bodies[0])
                .chain(objs.iter().copied())
                .collect(),
        );
        let top = doc.root.push(top);
        chars.push(Character {
            top,
            bodies,
            objects: objs,
        });
    }
    let scene = doc.root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        name: Some("skillaug".into()),
        nodes: chars.iter().map(|c| c.top).collect(),
    });
    doc.root.scene = Some(scene);

    // visibility keys, made when first needed
    let hide_chars = motions.iter().any(|m| m.tracks.len() < n_chars);
    let hide_objects = slots
        .iter()
        .any(|s| (0..objects.len()).any(|j| !s.contains(&j)));
    let mut once: Option<(
        Index<json::Accessor>,
        Index<json::Accessor>,
        Index<json::Accessor>,
    )> = None;
    let mut visibility = |doc: &mut Doc| {
        *once.get_or_insert_with(|| {
            (
                doc.floats(&[0.0], 1, true, None),
                doc.floats(&[1.0; 3], 3, false, None),
                doc.floats(&[0.0; 3], 3, false, None),
            )
        })
    };

    use json::animation::{Interpolation, Property};
    for (m, slot) in motions.iter().zip(&slots) {
        let mut a = Anim {
            channels: Vec::new(),
            samplers: Vec::new(),
        };
        let mut times: HashMap<usize, Index<json::Accessor>> = HashMap::new();
        for (k, c) in chars.iter().enumerate() {
            let Some(track) = m.tracks.get(k) else {
                let (t0, _, zero) = visibility(&mut doc);
                a.add(c.top, Property::Scale, t0, zero, Interpolation::Step);
                continue;
            };
            if hide_chars {
                let (t0, one, _) = visibility(&mut doc);
                a.add(c.top, Property::Scale, t0, one, Interpolation::Step);
            }
            let frames = held(track, nb, slot.len()).with_context(|| m.title.clone())?;
            let n = frames.len();
            let input = match times.get(&n) {
                Some(t) => *t,
                None => {
                    let t: Vec<f32> = (0..n).map(|i| (i as f64 / m.fps) as f32).collect();
                    if t.windows(2).any(|w| w[1] <= w[0]) {
                        bail!(
                            "{}: {n} frames at {} fps give times f32 cannot order",
                            m.title,
                            m.fps
                        );
                    }
                    let acc = doc.floats(&t, 1, true, None);
                    times.insert(n, acc);
                    acc
                }
            };
            let root_t: Vec<f32> = frames
                .iter()
                .flat_map(|p| y_up(p.root_pos.map(|v| v as f64)).map(|v| v as f32))
                .collect();
            let out = doc.floats(&root_t, 3, false, None);
            a.add(
                c.bodies[0],
                Property::Translation,
                input,
                out,
                Interpolation::Linear,
            );
            for b in 0..nb {
                let keys = rotation_keys(frames.iter().map(|p| {
                    if b == 0 {
                        quat::mul(Z_UP_TO_Y_UP, unit(p.root_rot))
                    } else {
                        let e = &p.joint_rot[3 * (b - 1)..3 * b];
                        quat::from_expmap([e[0] as f64, e[1] as f64, e[2] as f64])
                    }
                }));
                let out = doc.floats(&keys, 4, false, None);
                a.add(
                    c.bodies[b],
                    Property::Rotation,
                    input,
                    out,
                    Interpolation::Linear,
                );
            }
            for (j, node) in c.objects.iter().enumerate() {
                let Some(s) = slot.iter().position(|&x| x == j) else {
                    let (t0, _, zero) = visibility(&mut doc);
                    a.add(*node, Property::Scale, t0, zero, Interpolation::Step);
                    continue;
                };
                if hide_objects {
                    let (t0, one, _) = visibility(&mut doc);
                    a.add(*node, Property::Scale, t0, one, Interpolation::Step);
                }
                let tr: Vec<f32> = frames
                    .iter()
                    .flat_map(|p| {
                        let o = &p.obj_pos[3 * s..3 * s + 3];
                        y_up([o[0] as f64, o[1] as f64, o[2] as f64]).map(|v| v as f32)
                    })
                    .collect();
                let out = doc.floats(&tr, 3, false, None);
                a.add(
                    *node,
                    Property::Translation,
                    input,
                    out,
                    Interpolation::Linear,
                );
                let keys = rotation_keys(frames.iter().map(|p| {
                    let q = &p.obj_rot[4 * s..4 * s + 4];
                    quat::mul(Z_UP_TO_Y_UP, unit([q[0], q[1], q[2], q[3]]))
                }));
                let out = doc.floats(&keys, 4, false, None);
                a.add(*node, Property::Rotation, input, out, Interpolation::Linear);
            }
        }
        doc.root.push(json::Animation {
            extensions: None,
            extras: Default::default(),
            channels: a.channels,
            name: Some(m.title.clone()),
            samplers: a.samplers,
        });
    }

    while !doc.bin.len().is_multiple_of(4) {
        doc.bin.push(0);
    }
    doc.root.push(json::Buffer {
        byte_length: USize64::from(doc.bin.len()),
        name: None,
        uri: None,
        extensions: None,
        extras: Default::default(),
    });
    let mut problems = Vec::new();
    {
        use json::validation::Validate;
        doc.root
            .validate(&doc.root, json::Path::new, &mut |path, err| {
                problems.push(format!("{}: {err:?}", path().0))
            });
    }
    if !problems.is_empty() {
        bail!(
            "the glTF document fails validation: {}",
            problems.join("; ")
        );
    }
    let text = doc.root.to_vec().context("serialising the glTF document")?;
    glb_container(&text, &doc.bin)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Six times the signed volume enclosed by a closed mesh (positive when
    /// its triangles wind counter-clockwise seen from outside).
    fn volume6(m: &MeshData) -> f64 {
        m.idx
            .chunks_exact(3)
            .map(|t| {
                let [a, b, c] = [0, 1, 2].map(|k| m.pos[t[k] as usize].map(|v| v as f64));
                a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                    + a[2] * (b[0] * c[1] - b[1] * c[0])
            })
            .sum()
    }

    fn mesh_of(kind: &'static str, size: [f32; 3]) -> MeshData {
        let g = GeomView {
            kind,
            size,
            pos: [0.1, 0.2, -0.3],
            quat: [0.0, 0.0, 0.38268343, 0.9238795],
        };
        let (s, p) = geom_shape(&g).unwrap();
        let (mut v, mut t) = (Vec::new(), Vec::new());
        shape_mesh(&s, p, &mut v, &mut t);
        let mut m = MeshData::default();
        m.add(&v, &t);
        m
    }

    #[test]
    fn geom_meshes_are_closed_outward_and_the_right_size() {
        use std::f64::consts::PI;
        for (kind, size, vol) in [
            ("sphere", [0.1, 0.0, 0.0], 4.0 / 3.0 * PI * 1e-3),
            ("box", [0.1, 0.2, 0.05], 8.0 * 0.1 * 0.2 * 0.05),
            (
                "capsule",
                [0.05, 0.2, 0.0],
                PI * 0.0025 * 0.4 + 4.0 / 3.0 * PI * 0.05f64.powi(3),
            ),
            ("cylinder", [0.05, 0.2, 0.0], PI * 0.0025 * 0.4),
        ] {
            let m = mesh_of(kind, size);
            let v = volume6(&m) / 6.0;
            // tessellated curved shapes are a little smaller
            assert!(
                v > 0.9 * vol && v < 1.0001 * vol,
                "{kind}: volume {v} vs {vol}"
            );
            for (p, n) in m.pos.iter().zip(&m.nrm) {
                let l = n.iter().map(|x| x * x).sum::<f32>().sqrt();
                assert!((l - 1.0).abs() < 1e-5, "{kind}: normal length {l}");
                // outward: from the centre towards the vertex
                let d = [p[0] - 0.1, p[1] - 0.2, p[2] + 0.3];
                assert!(
                    d[0] * n[0] + d[1] * n[1] + d[2] * n[2] > 0.0,
                    "{kind}: inward normal"
                );
            }
        }
        // boxes keep sharp edges: 6 faces x 4 corners
        assert_eq!(mesh_of("box", [0.1, 0.2, 0.05]).pos.len(), 24);
    }

    #[test]
    fn capsules_lie_along_the_rotated_z_axis() {
        // no rotation: a capsule of half length 0.2 and radius 0.05 spans z
        let g = GeomView {
            kind: "capsule",
            size: [0.05, 0.2, 0.0],
            pos: [0.0; 3],
            quat: [0.0, 0.0, 0.0, 1.0],
        };
        let (s, p) = geom_shape(&g).unwrap();
        let (mut v, mut t) = (Vec::new(), Vec::new());
        shape_mesh(&s, p, &mut v, &mut t);
        let zmax = v.chunks_exact(3).map(|p| p[2]).fold(f32::MIN, f32::max);
        let xmax = v.chunks_exact(3).map(|p| p[0]).fold(f32::MIN, f32::max);
        assert!(
            (zmax - 0.25).abs() < 1e-5 && (xmax - 0.05).abs() < 1e-3,
            "{zmax} {xmax}"
        );
        let g = GeomView {
            kind: "cylinder",
            ..g
        };
        let (s, p) = geom_shape(&g).unwrap();
        let (mut v, mut t) = (Vec::new(), Vec::new());
        shape_mesh(&s, p, &mut v, &mut t);
        let zmax = v.chunks_exact(3).map(|p| p[2]).fold(f32::MIN, f32::max);
        assert!((zmax - 0.2).abs() < 1e-5, "{zmax}");
    }

    #[test]
    fn container_pads_chunks_to_four_bytes() {
        let g = glb_container(b"{\"a\":1}", &[1, 2, 3, 4, 5]).unwrap();
        assert_eq!(&g[0..4], b"glTF");
        assert_eq!(u32::from_le_bytes(g[4..8].try_into().unwrap()), 2);
        assert_eq!(
            u32::from_le_bytes(g[8..12].try_into().unwrap()) as usize,
            g.len()
        );
        assert_eq!(u32::from_le_bytes(g[12..16].try_into().unwrap()), 8);
        assert_eq!(&g[16..20], b"JSON");
        assert_eq!(&g[20..28], b"{\"a\":1} ");
        assert_eq!(u32::from_le_bytes(g[28..32].try_into().unwrap()), 8);
        assert_eq!(&g[32..36], b"BIN\0");
        assert_eq!(&g[36..44], &[1, 2, 3, 4, 5, 0, 0, 0]);
        assert_eq!(g.len() % 4, 0);
    }

    fn posture(x: f32, bend: f32, ball: f32) -> crate::motion::state::Posture {
        crate::motion::state::Posture {
            root_pos: [x, 0.5, 1.0],
            root_rot: [0.0, 0.0, 0.0, 1.0],
            joint_rot: vec![0.0, 0.0, bend],
            obj_pos: vec![ball, 0.0, 0.12],
            obj_rot: vec![0.0, 0.0, 0.0, 1.0],
        }
    }

    fn track(
        name: &str,
        frames: Vec<Option<crate::motion::state::Posture>>,
    ) -> super::super::motions::Track {
        super::super::motions::Track {
            name: name.into(),
            frames,
            masked: Vec::new(),
            value: None,
        }
    }

    const TINY: &str = r#"<mujoco><worldbody>
        <body name="root" pos="0 0 1"><geom type="sphere" size="0.1"/>
          <body name="arm" pos="0.3 0 0"><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04"/></body>
        </body></worldbody></mujoco>"#;

    fn json_of(glb: &[u8]) -> serde_json::Value {
        let n = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
        serde_json::from_slice(&glb[20..20 + n]).unwrap()
    }

    #[test]
    fn two_tracks_make_two_characters_and_absent_ones_are_hidden() {
        let model = Model::parse(TINY).unwrap();
        let two = Motion {
            title: "rollout".into(),
            stem: "r".into(),
            skill: "run".into(),
            note: String::new(),
            fps: 30.0,
            objects: vec!["ball".into()],
            tracks: vec![
                track(
                    "rollout",
                    vec![Some(posture(0.0, 0.0, 1.0)), Some(posture(0.1, 0.5, 1.1))],
                ),
                track("reference", vec![None, Some(posture(0.2, 1.0, 1.2)), None]),
            ],
        };
        let one = Motion {
            title: "clip".into(),
            objects: vec![],
            tracks: vec![track("reference", vec![Some(posture(0.0, 0.0, 0.0)); 4])],
            ..two.clone()
        };
        let glb = to_glb(&model, &[ObjectSpec::ball()], &[two, one]).unwrap();
        let doc = json_of(&glb);
        let scene = doc["scenes"][0]["nodes"].as_array().unwrap();
        assert_eq!(scene.len(), 2);
        let c1 = &doc["nodes"][scene[1].as_u64().unwrap() as usize];
        assert_eq!(c1["name"], "character 1: reference");
        assert_eq!(c1["translation"], serde_json::json!([1.5, 0.0, 0.0]));
        let names: Vec<&str> = doc["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| n["name"].as_str().unwrap())
            .collect();
        assert_eq!(
            names,
            [
                "root",
                "arm",
                "ball",
                "character 0: rollout / reference",
                "root.1",
                "arm.1",
                "ball.1",
                "character 1: reference"
            ]
        );
        assert_eq!(
            doc["nodes"][1]["translation"],
            serde_json::json!([0.3, 0.0, 0.0])
        );
        let anims = doc["animations"].as_array().unwrap();
        assert_eq!(anims.len(), 2);
        // scale keys: (node, value) per animation
        let scales = |a: &serde_json::Value| -> Vec<(u64, f64)> {
            a["channels"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|c| c["target"]["path"] == "scale")
                .map(|c| {
                    let s = &a["samplers"][c["sampler"].as_u64().unwrap() as usize];
                    assert_eq!(s["interpolation"], "STEP");
                    let acc = s["output"].as_u64().unwrap() as usize;
                    let v = &doc["bufferViews"]
                        [doc["accessors"][acc]["bufferView"].as_u64().unwrap() as usize];
                    let off = 20
                        + u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize
                        + 8
                        + v["byteOffset"].as_u64().unwrap() as usize;
                    (
                        c["target"]["node"].as_u64().unwrap(),
                        f32::from_le_bytes(glb[off..off + 4].try_into().unwrap()) as f64,
                    )
                })
                .collect()
        };
        // the two-track motion shows both characters and their balls
        assert_eq!(scales(&anims[0]), [(3, 1.0), (2, 1.0), (7, 1.0), (6, 1.0)]);
        // the clip hides character 1 and character 0's ball
        assert_eq!(scales(&anims[1]), [(3, 1.0), (2, 0.0), (7, 0.0)]);
        // the reference's leading missing frame holds its first valid one:
        // three keys, root at x = 0.2 each time; y up: (x, z, -y)
        let ch = anims[0]["channels"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["target"]["node"] == 4 && c["target"]["path"] == "translation")
            .unwrap();
        let s = &anims[0]["samplers"][ch["sampler"].as_u64().unwrap() as usize];
        let out = &doc["accessors"][s["output"].as_u64().unwrap() as usize];
        assert_eq!(out["count"], 3);
        let input = &doc["accessors"][s["input"].as_u64().unwrap() as usize];
        assert_eq!(input["max"], serde_json::json!([2.0f32 / 30.0]));
        let v = &doc["bufferViews"][out["bufferView"].as_u64().unwrap() as usize];
        let off = 20
            + u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize
            + 8
            + v["byteOffset"].as_u64().unwrap() as usize;
        let f: Vec<f32> = (0..9)
            .map(|k| f32::from_le_bytes(glb[off + 4 * k..off + 4 * k + 4].try_into().unwrap()))
            .collect();
        assert_eq!(f, [0.2, 1.0, -0.5, 0.2, 1.0, -0.5, 0.2, 1.0, -0.5]);
    }

    #[test]
    fn refuses_what_it_cannot_export() {
        let model = Model::parse(TINY).unwrap();
        let m = Motion {
            title: "t".into(),
            stem: "t".into(),
            skill: "s".into(),
            note: String::new(),
            fps: 30.0,
            objects: vec!["kettle".into()],
            tracks: vec![track("reference", vec![Some(posture(0.0, 0.0, 0.0))])],
        };
        let e = to_glb(&model, &[ObjectSpec::ball()], std::slice::from_ref(&m)).unwrap_err();
        assert!(
            format!("{e:#}").contains("no shape given for object `kettle`"),
            "{e:#}"
        );
        let e = to_glb(&model, &[], &[]).unwrap_err();
        assert!(format!("{e:#}").contains("no motion"));
        let bad = Motion {
            objects: vec![],
            tracks: vec![track("reference", vec![None, None])],
            ..m.clone()
        };
        let e = to_glb(&model, &[], &[bad]).unwrap_err();
        assert!(format!("{e:#}").contains("no valid frame"), "{e:#}");
        let mut p = posture(0.0, 0.0, 0.0);
        p.joint_rot.push(0.0);
        let bad = Motion {
            objects: vec![],
            tracks: vec![track("reference", vec![Some(p)])],
            ..m.clone()
        };
        let e = to_glb(&model, &[], &[bad]).unwrap_err();
        assert!(
            format!("{e:#}").contains("4 joint values for a model of 2 bodies"),
            "{e:#}"
        );
        let bad = Motion {
            objects: vec![],
            fps: 0.0,
            ..m
        };
        let e = to_glb(&model, &[], &[bad]).unwrap_err();
        assert!(format!("{e:#}").contains("frame rate 0"), "{e:#}");
    }

    #[test]
    fn rotation_keys_take_the_short_way() {
        let q = [0.0, 0.0, 0.1, 0.995];
        let k = rotation_keys([q, quat::neg(q), q].into_iter());
        assert!(k[3] > 0.0 && k[7] > 0.0 && k[11] > 0.0);
        let n: f32 = k[..4].iter().map(|x| x * x).sum();
        assert!((n - 1.0).abs() < 1e-6);
    }
}
