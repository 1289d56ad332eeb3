//! The humanoid models in MJCF (`mocap_humanoid.xml`, 53 bodies;
//! `mocap_parahome_boxhand.xml`, 61 bodies), read with our own small reader
//! over `roxmltree`: only bodies, their offsets, hinge joints (gains,
//! armature) and geoms are needed, and the BallPlay files carry
//! `density=""`, which strict MJCF parsers reject (read here as "default
//! density", `None`). Body order is depth-first document order, the order of
//! the data (reference §2.1).

use anyhow::{anyhow, bail, Context, Result};
use std::path::Path;

/// One geom, as written in the file (local to its body).
#[derive(Clone, Debug, PartialEq)]
pub struct Geom {
    /// `capsule`, `sphere` or `box` (default `capsule`, from the file's defaults).
    pub kind: String,
    /// `size` values.
    pub size: Vec<f64>,
    /// `fromto` of a capsule, if given.
    pub fromto: Option<[f64; 6]>,
    /// `pos`.
    pub pos: [f64; 3],
    /// `quat` (w, x, y, z as MJCF writes it).
    pub quat: Option<[f64; 4]>,
    /// `density`, kg/m^3 (`None` when absent or empty).
    pub density: Option<f64>,
}

/// One hinge joint.
#[derive(Clone, Debug, PartialEq)]
pub struct Hinge {
    /// Joint name.
    pub name: String,
    /// Axis in the body frame.
    pub axis: [f64; 3],
    /// PD stiffness kp.
    pub stiffness: f64,
    /// PD damping kd.
    pub damping: f64,
    /// Armature.
    pub armature: f64,
}

/// One body.
#[derive(Clone, Debug, PartialEq)]
pub struct Body {
    /// Body name.
    pub name: String,
    /// Parent index (`None` for the root).
    pub parent: Option<usize>,
    /// Offset from the parent, in the parent's frame, m.
    pub pos: [f64; 3],
    /// Hinges (three per non-root body in these models).
    pub hinges: Vec<Hinge>,
    /// Geoms.
    pub geoms: Vec<Geom>,
}

/// A humanoid model.
#[derive(Clone, Debug, PartialEq)]
pub struct Model {
    /// Bodies in depth-first order.
    pub bodies: Vec<Body>,
}

fn floats(s: &str, what: &str) -> Result<Vec<f64>> {
    s.split_whitespace()
        .map(|t| t.parse::<f64>().map_err(|e| anyhow!("{what}: `{t}`: {e}")))
        .collect()
}

fn arr<const N: usize>(v: Vec<f64>, what: &str) -> Result<[f64; N]> {
    v.try_into()
        .map_err(|v: Vec<f64>| anyhow!("{what}: {} numbers, expected {N}", v.len()))
}

impl Model {
    /// Read an MJCF file.
    pub fn load(path: &Path) -> Result<Model> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read the humanoid model {}", path.display()))?;
        Model::parse(&text).with_context(|| format!("{}", path.display()))
    }

    /// Parse MJCF text.
    pub fn parse(text: &str) -> Result<Model> {
        let doc = roxmltree::Document::parse(text)?;
        let world = doc
            .descendants()
            .find(|n| n.has_tag_name("worldbody"))
            .ok_or_else(|| anyhow!("no <worldbody>"))?;
        let root = world
            .children()
            .find(|n| n.has_tag_name("body"))
            .ok_or_else(|| anyhow!("<worldbody> has no <body>"))?;
        let mut bodies = Vec::new();
        walk(root, None, &mut bodies)?;
        Ok(Model { bodies })
    }

    /// A copy without the bodies for which `drop` is true, nor their
    /// descendants (for example the fingers, for a lighter model), and the
    /// original index of each body kept.
    pub fn without(&self, drop: impl Fn(&Body) -> bool) -> (Model, Vec<usize>) {
        let mut new_index = vec![None; self.bodies.len()];
        let mut bodies = Vec::new();
        let mut kept = Vec::new();
        for (i, b) in self.bodies.iter().enumerate() {
            let parent = match b.parent {
                None => None,
                Some(p) => match new_index[p] {
                    None => continue,
                    some => some,
                },
            };
            if drop(b) {
                continue;
            }
            new_index[i] = Some(bodies.len());
            kept.push(i);
            bodies.push(Body {
                parent,
                ..b.clone()
            });
        }
        (Model { bodies }, kept)
    }

    /// The model for a skeleton from the data root's `assets/mjcf`, checked
    /// against the skeleton's body names and order.
    pub fn for_skeleton(
        data_root: &Path,
        skeleton: crate::motion::layout::Skeleton,
    ) -> Result<Model> {
        let path = data_root
            .join("assets/mjcf")
            .join(format!("{}.xml", skeleton.name()));
        let m = Model::load(&path)?;
        if m.names() != skeleton.body_names() {
            bail!(
                "{}: body names or order differ from the {} skeleton",
                path.display(),
                skeleton
            );
        }
        Ok(m)
    }

    /// Body names in order.
    pub fn names(&self) -> Vec<&str> {
        self.bodies.iter().map(|b| b.name.as_str()).collect()
    }
}

fn walk(node: roxmltree::Node, parent: Option<usize>, out: &mut Vec<Body>) -> Result<()> {
    let name = node.attribute("name").unwrap_or("").to_string();
    let what = |a: &str| format!("body `{name}` {a}");
    let pos = match node.attribute("pos") {
        Some(p) => arr(floats(p, &what("pos"))?, &what("pos"))?,
        None => [0.0; 3],
    };
    if node.attribute("quat").is_some() || node.attribute("euler").is_some() {
        bail!("body `{name}` has an orientation attribute; only position offsets are supported");
    }
    let mut hinges = Vec::new();
    let mut geoms = Vec::new();
    for c in node.children().filter(|c| c.is_element()) {
        match c.tag_name().name() {
            "joint" if c.attribute("type").unwrap_or("hinge") == "hinge" => {
                let g = |a: &str| -> Result<f64> {
                    c.attribute(a).map_or(Ok(0.0), |v| {
                        v.trim().parse().map_err(|e| anyhow!("{}: {e}", what(a)))
                    })
                };
                hinges.push(Hinge {
                    name: c.attribute("name").unwrap_or("").to_string(),
                    axis: arr(
                        floats(c.attribute("axis").unwrap_or("0 0 1"), &what("axis"))?,
                        &what("axis"),
                    )?,
                    stiffness: g("stiffness")?,
                    damping: g("damping")?,
                    armature: g("armature")?,
                });
            }
            "geom" => {
                let density = match c.attribute("density").map(str::trim) {
                    None | Some("") => None,
                    Some(d) => Some(
                        d.parse()
                            .map_err(|e| anyhow!("{}: {e}", what("geom density")))?,
                    ),
                };
                geoms.push(Geom {
                    kind: c.attribute("type").unwrap_or("capsule").to_string(),
                    size: floats(c.attribute("size").unwrap_or(""), &what("geom size"))?,
                    fromto: c
                        .attribute("fromto")
                        .map(|f| arr(floats(f, &what("fromto"))?, &what("fromto")))
                        .transpose()?,
                    pos: match c.attribute("pos") {
                        Some(p) => arr(floats(p, &what("geom pos"))?, &what("geom pos"))?,
                        None => [0.0; 3],
                    },
                    quat: c
                        .attribute("quat")
                        .map(|q| arr(floats(q, &what("geom quat"))?, &what("geom quat")))
                        .transpose()?,
                    density,
                });
            }
            _ => {}
        }
    }
    let me = out.len();
    out.push(Body {
        name,
        parent,
        pos,
        hinges,
        geoms,
    });
    for c in node.children().filter(|c| c.has_tag_name("body")) {
        walk(c, Some(me), out)?;
    }
    Ok(())
}

/// Forward kinematics with exp-map joints (reference §1.4): each non-root
/// body's local rotation is `quat_from_expmap(its joint triple)`; returns
/// world body positions `[B*3]`.
pub fn forward_kinematics(
    m: &Model,
    root_pos: [f32; 3],
    root_rot: [f32; 4],
    joint_rot: &[f32],
) -> Vec<f32> {
    body_poses(m, root_pos, root_rot, joint_rot).0
}

/// [`forward_kinematics`] with the world rotations too: body positions
/// `[B*3]` and unit quaternions (x, y, z, w) `[B*4]`.
pub fn body_poses(
    m: &Model,
    root_pos: [f32; 3],
    root_rot: [f32; 4],
    joint_rot: &[f32],
) -> (Vec<f32>, Vec<f32>) {
    use crate::motion::quat;
    let n = m.bodies.len();
    let mut rot = vec![quat::IDENTITY; n];
    let mut pos = vec![[0.0f64; 3]; n];
    for (i, b) in m.bodies.iter().enumerate() {
        match b.parent {
            None => {
                rot[i] = root_rot.map(|v| v as f64);
                pos[i] = root_pos.map(|v| v as f64);
            }
            Some(p) => {
                let j = &joint_rot[3 * (i - 1)..3 * i];
                let local = quat::from_expmap([j[0] as f64, j[1] as f64, j[2] as f64]);
                rot[i] = quat::mul(rot[p], local);
                let o = quat::rotate(rot[p], b.pos);
                pos[i] = [pos[p][0] + o[0], pos[p][1] + o[1], pos[p][2] + o[2]];
            }
        }
    }
    (
        pos.iter().flat_map(|p| p.map(|v| v as f32)).collect(),
        rot.iter().flat_map(|q| q.map(|v| v as f32)).collect(),
    )
}
