//! The humanoid models in MJCF (`mocap_humanoid.xml`, 53 bodies;
//! `mocap_parahome_boxhand.xml`, 61 bodies), read with our own small reader
//! over `roxmltree`: only bodies, their offsets, hinge joints (gains,
//! armature) and geoms are needed. Body order is depth-first document order,
//! the order of the data (the clips of Ingrid789/SkillMimic-V2; its reward
//! code, `skillmimic/env/tasks/skillmimic1.py`, lists the BallPlay bodies in
//! this order).
//!
//! MuJoCo's default mechanism applies to every attribute read here: the
//! top-level `<default>` is class "main" (several top-level sections amend
//! it), a nested `<default class="…">` starts from its parent class's values
//! and overrides some, and a `<joint>` or `<geom>` takes the class named by
//! its `class`, else the `childclass` of the nearest enclosing `<body>` that
//! has one (the body itself included), else "main". The element's own
//! attributes win over the class's; a `size` with fewer numbers than the
//! class's keeps the class's remaining ones, as MuJoCo does. Where neither
//! says anything, MuJoCo's built-in values hold: geom type `sphere`, geom
//! position 0 and no rotation, density `None` (1000 in the world), joint type
//! `hinge`, axis `0 0 1`, stiffness, damping and armature 0.
//!
//! The BallPlay files carry `density=""`, which strict MJCF parsers reject;
//! it is read here as "not given" (the class's density if it has one, else
//! `None`).
//!
//! Refused, naming the body (and the geom's index among the body's geoms, or
//! the joint's name): a number that is not finite (`nan`, `inf`), a count of
//! numbers other than the attribute takes (`size`: at most three), an unknown class or childclass,
//! an unknown geom or joint type, a missing or non-positive size where the
//! geom type needs one (sphere: radius; capsule and cylinder: radius, plus
//! the half-length without `fromto`; box and ellipsoid: three half-sizes), a
//! density of 0 or below, a quaternion or joint axis of norm under 1e-9, a
//! `fromto` shorter than 1e-9 or beside a non-zero `pos`, or on another type
//! than capsule and cylinder (the only ones the world builds from it),
//! negative stiffness, damping or armature, and what this reader would
//! otherwise drop without a word: geom `mass`, orientations other than
//! `quat`, `<frame>`, `<include>`, `<replicate>`, `<attach>` and
//! `compiler coordinate="global"`.
//!
//! We do not use `rapier3d-mjcf` (0.36.1, the release for our rapier3d
//! 0.36; checked in its source and by running its parser `mjcf-rs` 0.36.1 on
//! the shipped humanoid): its parser keeps the body order (depth-first, after a
//! world body at index 0), applies default classes and `childclass` and
//! exposes joint stiffness, damping and armature, but it refuses the shipped
//! `mocap_humanoid.xml` outright (`density=""`: "cannot parse float from
//! empty string") and accepts without a word an unknown class (it falls back
//! to "main"), a `nan` size, a negative density and a zero quaternion (read as
//! the identity), so the checks here would be needed anyway. Its converter
//! builds its own rapier bodies and joints (an intermediate body per extra
//! joint, stiffness and damping as joint motors) where [`super::world`] builds
//! one spherical joint per body with its own PD drive, so only the parser
//! would be of use, at the cost of one more crate (`mjcf-rs`; `glamx` and
//! `roxmltree` are in the build already), a pre-pass over the text for
//! `density=""` and a mapping from its types to ours.

use anyhow::{anyhow, bail, Context, Result};
use std::collections::HashMap;
use std::path::Path;

/// One geom, with the default classes applied (local to its body).
#[derive(Clone, Debug, PartialEq)]
pub struct Geom {
    /// MuJoCo geom type (default `sphere`, MuJoCo's built-in value; the shipped
    /// files set `capsule` in their top-level default class). The world builds
    /// `capsule` and `cylinder` (from `fromto`), `sphere` and `box`, and
    /// refuses the others.
    pub kind: String,
    /// `size` values (at most three, all finite).
    pub size: Vec<f64>,
    /// `fromto` of a capsule or cylinder, if given.
    pub fromto: Option<[f64; 6]>,
    /// `pos`.
    pub pos: [f64; 3],
    /// `quat` (w, x, y, z as MJCF writes it; norm at least 1e-9, not normalised).
    pub quat: Option<[f64; 4]>,
    /// `density`, kg/m^3, positive (`None` when absent or empty).
    pub density: Option<f64>,
}

/// One hinge joint.
#[derive(Clone, Debug, PartialEq)]
pub struct Hinge {
    /// Joint name.
    pub name: String,
    /// Axis in the body frame (norm at least 1e-9, not normalised).
    pub axis: [f64; 3],
    /// PD stiffness kp (not negative).
    pub stiffness: f64,
    /// PD damping kd (not negative).
    pub damping: f64,
    /// Armature (not negative).
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

/// MuJoCo's geom types (XML reference, `geom/type`).
const GEOM_TYPES: [&str; 9] = [
    "plane",
    "hfield",
    "sphere",
    "capsule",
    "ellipsoid",
    "cylinder",
    "box",
    "mesh",
    "sdf",
];

/// MuJoCo's joint types (XML reference, `joint/type`).
const JOINT_TYPES: [&str; 4] = ["free", "ball", "slide", "hinge"];

/// Orientation attributes other than `quat`, which this reader does not convert.
const OTHER_ORIENTATIONS: [&str; 4] = ["axisangle", "euler", "xyaxes", "zaxis"];

/// Elements of the body tree that add or move bodies, joints or geoms in ways
/// this reader does not follow.
/// (`<include>` is refused anywhere in the document before the bodies are read.)
const UNSUPPORTED_IN_BODY: [&str; 3] = ["frame", "replicate", "attach"];

/// Smallest norm accepted for a quaternion or a joint axis, and length for a
/// `fromto`.
const MIN_NORM: f64 = 1e-9;

/// Whitespace-separated numbers, all finite.
fn floats(s: &str, what: &str) -> Result<Vec<f64>> {
    s.split_whitespace()
        .map(|t| {
            let v: f64 = t.parse().map_err(|e| anyhow!("{what}: `{t}`: {e}"))?;
            if !v.is_finite() {
                bail!("{what}: `{t}` is not a finite number");
            }
            Ok(v)
        })
        .collect()
}

fn arr<const N: usize>(v: Vec<f64>, what: &str) -> Result<[f64; N]> {
    v.try_into()
        .map_err(|v: Vec<f64>| anyhow!("{what}: {} numbers, expected {N}", v.len()))
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// The attribute values one default class sets for one element kind.
type Attrs = HashMap<String, String>;

/// One default class: the attributes of its dummy `<joint>` and `<geom>`
/// (its own and those inherited from its parent class).
#[derive(Clone, Debug, Default)]
struct Class {
    joint: Attrs,
    geom: Attrs,
}

/// The default classes of a file.
struct Defaults {
    /// Class name to its values.
    classes: HashMap<String, Class>,
    /// Name of the top-level class ("main" unless the file names it).
    top: String,
}

/// `size` written over an earlier `size`: MuJoCo keeps the earlier values
/// beyond those given.
fn merge_size(earlier: &str, given: &str) -> String {
    let mut t: Vec<&str> = given.split_whitespace().collect();
    let n = t.len();
    t.extend(earlier.split_whitespace().skip(n));
    t.join(" ")
}

/// An element's own value of `name`, with `density=""` read as absent.
fn own<'a>(node: roxmltree::Node<'a, '_>, name: &str) -> Option<&'a str> {
    node.attribute(name)
        .filter(|v| !(name == "density" && v.trim().is_empty()))
}

/// Write the attributes of `node` (a `<joint>` or `<geom>`) over `into`.
fn set_attrs(into: &mut Attrs, node: roxmltree::Node) {
    for a in node.attributes() {
        let name = a.name();
        if name == "name" || name == "class" {
            continue;
        }
        let Some(v) = own(node, name) else { continue };
        let v = match (name, into.get(name)) {
            ("size", Some(earlier)) => merge_size(earlier, v),
            _ => v.to_string(),
        };
        into.insert(name.to_string(), v);
    }
}

impl Defaults {
    /// The classes under the `<default>` sections that are children of `root`.
    fn read(root: roxmltree::Node) -> Result<Defaults> {
        let mut d = Defaults {
            classes: HashMap::new(),
            top: String::new(),
        };
        for section in root.children().filter(|n| n.has_tag_name("default")) {
            let name = section
                .attribute("class")
                .filter(|c| !c.is_empty())
                .unwrap_or("main");
            if d.top.is_empty() {
                d.top = name.to_string();
            } else if d.top != name {
                bail!(
                    "a top-level <default> names class `{name}`, another names `{}`; \
                     there is one top-level class",
                    d.top
                );
            }
            let class = d.classes.remove(name).unwrap_or_default();
            d.section(section, name, class)?;
        }
        if d.top.is_empty() {
            d.top = "main".to_string();
            d.classes.insert(d.top.clone(), Class::default());
        }
        Ok(d)
    }

    /// Read one `<default>` section into class `name`, starting from `class`
    /// (its parent's values, or its own from an earlier top-level section),
    /// then its nested classes, which start from this one's values.
    fn section(&mut self, section: roxmltree::Node, name: &str, mut class: Class) -> Result<()> {
        let (mut joint, mut geom) = (false, false);
        for e in section.children().filter(|n| n.is_element()) {
            let (seen, attrs) = match e.tag_name().name() {
                "joint" => (&mut joint, &mut class.joint),
                "geom" => (&mut geom, &mut class.geom),
                _ => continue,
            };
            if *seen {
                bail!(
                    "default class `{name}` has more than one <{}>",
                    e.tag_name().name()
                );
            }
            *seen = true;
            set_attrs(attrs, e);
        }
        self.classes.insert(name.to_string(), class.clone());
        for sub in section.children().filter(|n| n.has_tag_name("default")) {
            let sub_name = sub.attribute("class").unwrap_or("");
            if sub_name.is_empty() {
                bail!("a <default> inside class `{name}` has no class name");
            }
            if self.classes.contains_key(sub_name) {
                bail!("default class `{sub_name}` is defined twice");
            }
            self.section(sub, sub_name, class.clone())?;
        }
        Ok(())
    }

    /// The class an element uses: its own `class`, else the inherited
    /// `childclass`, else the top-level class.
    fn active(
        &self,
        node: roxmltree::Node,
        childclass: Option<&str>,
        what: &str,
    ) -> Result<&Class> {
        let name = node.attribute("class").or(childclass).unwrap_or(&self.top);
        self.classes
            .get(name)
            .ok_or_else(|| anyhow!("{what}: unknown default class `{name}`"))
    }
}

/// One `<joint>` or `<geom>` with the attributes of its active class.
struct Element<'a, 'input> {
    node: roxmltree::Node<'a, 'input>,
    class: &'a Attrs,
    what: String,
}

impl Element<'_, '_> {
    /// The value of attribute `name`: the element's own, else the class's.
    fn get(&self, name: &str) -> Option<String> {
        match (own(self.node, name), self.class.get(name)) {
            (Some(v), Some(earlier)) if name == "size" => Some(merge_size(earlier, v)),
            (Some(v), _) => Some(v.to_string()),
            (None, c) => c.cloned(),
        }
    }

    /// Numbers of attribute `name`, if set.
    fn floats(&self, name: &str) -> Result<Option<Vec<f64>>> {
        self.get(name)
            .map(|v| floats(&v, &format!("{} {name}", self.what)))
            .transpose()
    }

    /// Exactly `N` numbers of attribute `name`, if set.
    fn arr<const N: usize>(&self, name: &str) -> Result<Option<[f64; N]>> {
        self.floats(name)?
            .map(|v| arr(v, &format!("{} {name}", self.what)))
            .transpose()
    }

    /// One number, not negative, of attribute `name` (0 if not set).
    fn gain(&self, name: &str) -> Result<f64> {
        let v = self.arr::<1>(name)?.map_or(0.0, |[v]| v);
        if v < 0.0 {
            bail!("{} {name} is {v}; it must not be negative", self.what);
        }
        Ok(v)
    }

    /// Refuse attributes this reader would silently ignore.
    fn refuse(&self, names: &[&str], why: &str) -> Result<()> {
        for n in names {
            if self.get(n).is_some() {
                bail!("{} has `{n}`: {why}", self.what);
            }
        }
        Ok(())
    }
}

impl Model {
    /// Read an MJCF file.
    pub fn load(path: &Path) -> Result<Model> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read the humanoid model {}", path.display()))?;
        Model::parse(&text).with_context(|| format!("{}", path.display()))
    }

    /// Parse MJCF text, applying the default classes and refusing what the
    /// simulator would misbuild (module doc).
    pub fn parse(text: &str) -> Result<Model> {
        let doc = roxmltree::Document::parse(text)?;
        if doc.descendants().any(|n| n.has_tag_name("include")) {
            bail!("<include> is not supported; inline the included file");
        }
        for c in doc.descendants().filter(|n| n.has_tag_name("compiler")) {
            if let Some(coord) = c.attribute("coordinate").filter(|&v| v != "local") {
                bail!("compiler coordinate=\"{coord}\" is not supported (only local)");
            }
        }
        let defaults = Defaults::read(doc.root_element())?;
        let world = doc
            .descendants()
            .find(|n| n.has_tag_name("worldbody"))
            .ok_or_else(|| anyhow!("no <worldbody>"))?;
        let root = world
            .children()
            .find(|n| n.has_tag_name("body"))
            .ok_or_else(|| anyhow!("<worldbody> has no <body>"))?;
        let mut bodies = Vec::new();
        walk(root, None, None, &defaults, &mut bodies)?;
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

/// Read body `node` and its descendants, depth-first, into `out`;
/// `childclass` is the one the enclosing bodies hand down.
fn walk(
    node: roxmltree::Node,
    parent: Option<usize>,
    childclass: Option<&str>,
    defaults: &Defaults,
    out: &mut Vec<Body>,
) -> Result<()> {
    let name = node.attribute("name").unwrap_or("").to_string();
    let what = |a: &str| format!("body `{name}` {a}");
    let pos = match node.attribute("pos") {
        Some(p) => arr(floats(p, &what("pos"))?, &what("pos"))?,
        None => [0.0; 3],
    };
    if let Some(a) = ["quat"]
        .iter()
        .chain(&OTHER_ORIENTATIONS)
        .find(|a| node.attribute(**a).is_some())
    {
        bail!("body `{name}` has an orientation attribute (`{a}`); only position offsets are supported");
    }
    let childclass = match node.attribute("childclass") {
        Some(c) => {
            if !defaults.classes.contains_key(c) {
                bail!("body `{name}`: unknown default class `{c}` (childclass)");
            }
            Some(c)
        }
        None => childclass,
    };
    let mut hinges = Vec::new();
    let mut geoms = Vec::new();
    for c in node.children().filter(|c| c.is_element()) {
        match c.tag_name().name() {
            "joint" => {
                let jname = c.attribute("name").unwrap_or("").to_string();
                let what = format!("body `{name}` joint `{jname}`");
                let e = Element {
                    node: c,
                    class: &defaults.active(c, childclass, &what)?.joint,
                    what,
                };
                let kind = e.get("type").unwrap_or_else(|| "hinge".to_string());
                if !JOINT_TYPES.contains(&kind.as_str()) {
                    bail!("{}: unknown joint type `{kind}`", e.what);
                }
                if kind != "hinge" {
                    continue;
                }
                let axis = e.arr::<3>("axis")?.unwrap_or([0.0, 0.0, 1.0]);
                if norm(&axis) < MIN_NORM {
                    bail!("{}: axis {axis:?} has (almost) zero length", e.what);
                }
                hinges.push(Hinge {
                    name: jname,
                    axis,
                    stiffness: e.gain("stiffness")?,
                    damping: e.gain("damping")?,
                    armature: e.gain("armature")?,
                });
            }
            "geom" => {
                let what = format!("body `{name}` geom {}", geoms.len());
                let e = Element {
                    node: c,
                    class: &defaults.active(c, childclass, &what)?.geom,
                    what,
                };
                geoms.push(geom(&e)?);
            }
            t if UNSUPPORTED_IN_BODY.contains(&t) => {
                bail!("body `{name}` contains a <{t}>, which is not supported");
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
        walk(c, Some(me), childclass, defaults, out)?;
    }
    Ok(())
}

/// Read and check one geom.
fn geom(e: &Element) -> Result<Geom> {
    let what = &e.what;
    let kind = e.get("type").unwrap_or_else(|| "sphere".to_string());
    if !GEOM_TYPES.contains(&kind.as_str()) {
        bail!("{what}: unknown geom type `{kind}`");
    }
    e.refuse(
        &OTHER_ORIENTATIONS,
        "only `quat` orientations are supported",
    )?;
    e.refuse(&["mass"], "the world takes geom masses from `density`")?;
    let size = e.floats("size")?.unwrap_or_default();
    if size.len() > 3 {
        bail!("{what}: size has {} numbers, at most 3", size.len());
    }
    let fromto = e.arr::<6>("fromto")?;
    let pos = e.arr::<3>("pos")?.unwrap_or([0.0; 3]);
    let quat = e.arr::<4>("quat")?;
    if let Some(q) = quat {
        if norm(&q) < MIN_NORM {
            bail!("{what}: quat {q:?} has (almost) zero length");
        }
    }
    let density = match e.arr::<1>("density")? {
        Some([d]) if d <= 0.0 => bail!("{what}: density {d} must be positive"),
        d => d.map(|[d]| d),
    };
    if let Some(ft) = fromto {
        if !matches!(kind.as_str(), "capsule" | "cylinder") {
            bail!("{what}: `fromto` on a {kind} is not supported (capsule and cylinder only)");
        }
        let d = [ft[3] - ft[0], ft[4] - ft[1], ft[5] - ft[2]];
        if norm(&d) < MIN_NORM {
            bail!("{what}: the two `fromto` points coincide");
        }
        if pos != [0.0; 3] {
            bail!("{what}: both `pos` and `fromto` are given");
        }
    }
    let need: &[&str] = match (kind.as_str(), fromto.is_some()) {
        ("sphere", _) | ("capsule" | "cylinder", true) => &["radius"],
        ("capsule" | "cylinder", false) => &["radius", "half-length"],
        ("box", _) => &["x half-size", "y half-size", "z half-size"],
        ("ellipsoid", _) => &["x radius", "y radius", "z radius"],
        _ => &[],
    };
    if size.len() < need.len() {
        bail!(
            "{what}: a {kind}{} needs size {} ({} numbers), got {}",
            if fromto.is_some() { " with fromto" } else { "" },
            need.join(", "),
            need.len(),
            size.len()
        );
    }
    for (s, n) in size.iter().zip(need) {
        if *s <= 0.0 {
            bail!("{what}: size {n} is {s}; it must be positive");
        }
    }
    Ok(Geom {
        kind,
        size,
        fromto,
        pos,
        quat,
        density,
    })
}

impl crate::motion::Kinematics for Model {
    fn body_positions(
        &self,
        root_pos: [f32; 3],
        root_rot: [f32; 4],
        joint_rot: &[f32],
    ) -> Vec<f32> {
        forward_kinematics(self, root_pos, root_rot, joint_rot)
    }
}

/// Forward kinematics with exp-map joints (docs/simulation.md): each non-root
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A document with `defaults` as its `<default>` sections and `bodies`
    /// inside a root body `R`.
    fn doc(defaults: &str, bodies: &str) -> String {
        format!(
            "<mujoco>{defaults}<worldbody><body name=\"R\"><freejoint/>\
             <geom type=\"sphere\" size=\"0.1\"/>{bodies}</body></worldbody></mujoco>"
        )
    }

    fn parse(defaults: &str, bodies: &str) -> Model {
        Model::parse(&doc(defaults, bodies)).unwrap_or_else(|e| panic!("{e:#}"))
    }

    fn error(defaults: &str, bodies: &str) -> String {
        format!("{:#}", Model::parse(&doc(defaults, bodies)).unwrap_err())
    }

    fn gains(h: &Hinge) -> (f64, f64, f64) {
        (h.stiffness, h.damping, h.armature)
    }

    #[test]
    fn builtin_values_without_defaults() {
        let m = parse(
            "",
            r#"<body name="A"><joint name="j"/><geom size="0.2"/></body>"#,
        );
        let a = &m.bodies[1];
        assert_eq!(a.hinges[0].axis, [0.0, 0.0, 1.0]);
        assert_eq!(gains(&a.hinges[0]), (0.0, 0.0, 0.0));
        assert_eq!(a.geoms[0].kind, "sphere");
        assert_eq!(a.geoms[0].pos, [0.0; 3]);
        assert_eq!((a.geoms[0].quat, a.geoms[0].density), (None, None));
    }

    #[test]
    fn classes_childclass_and_own_attributes_in_mujoco_order() {
        let defaults = r#"<default>
              <joint stiffness="1" damping="2" armature="3"/>
              <geom type="capsule" size="0.05 0.2 0.3" density="900"/>
              <default class="a"><joint stiffness="10"/>
                <default class="b"><joint damping="20"/><geom density="800"/></default>
              </default>
              <default class="c"><joint armature="30" axis="1 0 0"/></default>
            </default>"#;
        let bodies = r#"<body name="A" childclass="a">
              <joint name="a0"/>
              <joint name="a1" class="main"/>
              <joint name="a2" class="c" damping="7"/>
              <geom size="0.01"/>
              <body name="B" childclass="b">
                <joint name="b0"/>
                <geom size="0.02 0.4" class="c" density=""/>
                <body name="C"><joint name="c0"/><geom type="box" size="1 2 3"/></body>
              </body>
            </body>"#;
        let m = parse(defaults, bodies);
        let [_, a, b, c] = &m.bodies[..] else {
            panic!("four bodies")
        };
        assert_eq!(gains(&a.hinges[0]), (10.0, 2.0, 3.0), "childclass a");
        assert_eq!(gains(&a.hinges[1]), (1.0, 2.0, 3.0), "own class main");
        assert_eq!(gains(&a.hinges[2]), (1.0, 7.0, 30.0), "class c and own");
        assert_eq!(a.hinges[2].axis, [1.0, 0.0, 0.0]);
        // a shorter size keeps the class's remaining numbers
        assert_eq!(a.geoms[0].size, vec![0.01, 0.2, 0.3]);
        assert_eq!(
            (a.geoms[0].kind.as_str(), a.geoms[0].density),
            ("capsule", Some(900.0))
        );
        assert_eq!(gains(&b.hinges[0]), (10.0, 20.0, 3.0), "nested class b");
        assert_eq!(b.geoms[0].size, vec![0.02, 0.4, 0.3]);
        assert_eq!(
            b.geoms[0].density,
            Some(900.0),
            "density=\"\" takes the class's"
        );
        assert_eq!(
            gains(&c.hinges[0]),
            (10.0, 20.0, 3.0),
            "childclass inherited"
        );
        assert_eq!(c.geoms[0].density, Some(800.0));
    }

    #[test]
    fn top_level_sections_amend_main_and_nested_classes_inherit_at_their_point() {
        let defaults = r#"<default><joint stiffness="1"/>
              <default class="x"><joint damping="5"/></default></default>
            <default><joint stiffness="2" armature="4"/></default>"#;
        let bodies = r#"<body name="A"><joint name="p"/><joint name="q" class="x"/></body>"#;
        let m = parse(defaults, bodies);
        assert_eq!(gains(&m.bodies[1].hinges[0]), (2.0, 0.0, 4.0));
        assert_eq!(gains(&m.bodies[1].hinges[1]), (1.0, 5.0, 0.0));
    }

    #[test]
    fn malformed_default_sections_are_refused() {
        let b = r#"<body name="A"><joint name="j"/></body>"#;
        let e = error(
            r#"<default><default class="x"/><default class="x"/></default>"#,
            b,
        );
        assert!(e.contains("`x` is defined twice"), "{e}");
        let e = error(r#"<default><default><joint/></default></default>"#, b);
        assert!(e.contains("no class name"), "{e}");
        let e = error(r#"<default><joint/><joint/></default>"#, b);
        assert!(e.contains("more than one <joint>"), "{e}");
        let e = error(r#"<default class="x"/><default class="y"/>"#, b);
        assert!(e.contains("top-level"), "{e}");
        let e = error(
            "",
            r#"<body name="A" childclass="main"><joint name="j" class="q"/></body>"#,
        );
        assert!(
            e.contains("body `A` joint `j`: unknown default class `q`"),
            "{e}"
        );
        let e = error(
            "",
            r#"<body name="A"><frame><geom size="1"/></frame></body>"#,
        );
        assert!(e.contains("body `A` contains a <frame>"), "{e}");
        let e = error(
            "",
            r#"<body name="A"><geom type="box" size="1 1 1" fromto="0 0 0 0 0 1"/></body>"#,
        );
        assert!(e.contains("body `A` geom 0: `fromto` on a box"), "{e}");
        let e = error(r#"<default><geom euler="0 0 1"/></default>"#, "");
        assert!(e.contains("body `R` geom 0 has `euler`"), "{e}");
    }

    #[test]
    fn capsule_sizes_depend_on_fromto() {
        let ok = parse(
            "",
            r#"<body name="A"><geom type="capsule" size="0.1 0.3"/></body>"#,
        );
        assert_eq!(ok.bodies[1].geoms[0].size, vec![0.1, 0.3]);
        let e = error(
            "",
            r#"<body name="A"><geom type="capsule" size="0.1"/></body>"#,
        );
        assert!(
            e.contains("body `A` geom 0: a capsule needs size radius, half-length"),
            "{e}"
        );
        let e = error(
            "",
            r#"<body name="A"><geom type="cylinder" size="0.1 -1"/></body>"#,
        );
        assert!(e.contains("half-length is -1"), "{e}");
        parse(
            "",
            r#"<body name="A"><geom type="cylinder" size="0.1 -1" fromto="0 0 0 0 0 1"/></body>"#,
        );
    }
}
