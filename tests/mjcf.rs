//! The MJCF reader against variants of the shipped humanoid files: the same
//! model written with MuJoCo's default classes must read the same, and
//! invalid geometry, masses and rotations must be refused naming the body.
//!
//! Each variant is built here from the shipped text with edits located by
//! `roxmltree` (attribute and element byte ranges), so the attributes really
//! move.

mod common;

use sha2::{Digest, Sha256};
use skillaug::sim::mjcf::Model;
use std::collections::HashMap;
use std::ops::Range;
use std::path::Path;
use std::process::Command;

const HUMANOID: &str = "mocap_humanoid.xml";
const PARAHOME: &str = "mocap_parahome_boxhand.xml";

fn shipped(name: &str) -> String {
    let path = common::data_root().join("assets/mjcf").join(name);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn parse(text: &str) -> Model {
    Model::parse(text).unwrap_or_else(|e| panic!("{e:#}"))
}

fn parse_err(text: &str) -> String {
    match Model::parse(text) {
        Ok(_) => panic!("parsed without an error"),
        Err(e) => format!("{e:#}"),
    }
}

/// One edit: replace the bytes in `range` by `text`.
type Edit = (Range<usize>, String);

/// Apply non-overlapping edits (from the end of the text backwards; at one
/// position a removal goes before an insertion).
fn apply(text: &str, mut edits: Vec<Edit>) -> String {
    edits.sort_by_key(|(r, _)| std::cmp::Reverse((r.start, r.end)));
    let mut out = text.to_string();
    let mut limit = text.len();
    for (r, s) in edits {
        assert!(r.end <= limit, "overlapping edits at {r:?}");
        out.replace_range(r.clone(), &s);
        limit = r.start;
    }
    out
}

/// Remove attribute `name` of `node`, with the whitespace before it.
fn remove_attr(text: &str, node: roxmltree::Node, name: &str) -> Edit {
    let a = node
        .attributes()
        .find(|a| a.name() == name)
        .unwrap_or_else(|| panic!("no `{name}` on <{}>", node.tag_name().name()));
    let r = a.range();
    let start = text[..r.start].trim_end().len();
    (start..r.end, String::new())
}

/// Add attribute `name="value"` right after the tag name of `node`.
fn add_attr(node: roxmltree::Node, name: &str, value: &str) -> Edit {
    let at = node.range().start + 1 + node.tag_name().name().len();
    (at..at, format!(" {name}=\"{value}\""))
}

/// Insert `inner` just inside the top-level `<default>` element.
fn into_top_default(text: &str, doc: &roxmltree::Document, inner: &str) -> Edit {
    let d = doc
        .root_element()
        .children()
        .find(|n| n.has_tag_name("default"))
        .expect("a top-level <default>");
    let at = d.range().start + text[d.range().start..].find('>').unwrap() + 1;
    (at..at, format!("\n{inner}"))
}

fn worldbody<'a, 'i>(doc: &'a roxmltree::Document<'i>) -> roxmltree::Node<'a, 'i> {
    doc.descendants()
        .find(|n| n.has_tag_name("worldbody"))
        .unwrap()
}

const GAINS: [&str; 3] = ["stiffness", "damping", "armature"];

/// (stiffness, damping, armature) as written on a joint.
type Triple = [String; 3];

fn triple(j: roxmltree::Node) -> Triple {
    GAINS.map(|g| j.attribute(g).unwrap().to_string())
}

/// The hinges of the body tree, in document order.
fn joints<'a, 'i>(doc: &'a roxmltree::Document<'i>) -> Vec<roxmltree::Node<'a, 'i>> {
    worldbody(doc)
        .descendants()
        .filter(|n| n.has_tag_name("joint"))
        .collect()
}

/// Distinct gain triples in order of first appearance, each with a class name.
fn triples(doc: &roxmltree::Document) -> Vec<(Triple, String)> {
    let mut out: Vec<(Triple, String)> = Vec::new();
    for j in joints(doc) {
        let t = triple(j);
        if !out.iter().any(|(u, _)| *u == t) {
            let name = format!("pd{}", out.len());
            out.push((t, name));
        }
    }
    out
}

fn class_of<'a>(classes: &'a [(Triple, String)], t: &Triple) -> &'a str {
    &classes.iter().find(|(u, _)| u == t).unwrap().1
}

fn joint_default(t: &Triple) -> String {
    format!(
        "<joint stiffness=\"{}\" damping=\"{}\" armature=\"{}\"/>",
        t[0], t[1], t[2]
    )
}

/// Edits removing the gains of every joint.
fn strip_gains(text: &str, doc: &roxmltree::Document) -> Vec<Edit> {
    joints(doc)
        .into_iter()
        .flat_map(|j| GAINS.map(|g| remove_attr(text, j, g)))
        .collect()
}

/// No joint of the body tree carries its gains any more.
fn assert_gains_moved(variant: &str) {
    let doc = roxmltree::Document::parse(variant).unwrap();
    for j in joints(&doc) {
        for g in GAINS {
            assert!(
                j.attribute(g).is_none(),
                "joint {:?} kept {g}",
                j.attribute("name")
            );
        }
    }
}

/// One `<default class>` per gain triple, holding its joint defaults.
fn class_defaults(classes: &[(Triple, String)]) -> String {
    classes
        .iter()
        .map(|(t, c)| format!("<default class=\"{c}\">{}</default>\n", joint_default(t)))
        .collect()
}

/// (a) One `<default class>` per distinct gain triple, referred to by `class=`.
fn by_class(text: &str) -> String {
    let doc = roxmltree::Document::parse(text).unwrap();
    let classes = triples(&doc);
    let mut edits = strip_gains(text, &doc);
    for j in joints(&doc) {
        edits.push(add_attr(j, "class", class_of(&classes, &triple(j))));
    }
    edits.push(into_top_default(text, &doc, &class_defaults(&classes)));
    apply(text, edits)
}

/// (b) The same classes, reached through `childclass` on the bodies: a body
/// sets one only where its joints' class differs from the one it inherits.
fn by_childclass(text: &str) -> String {
    let doc = roxmltree::Document::parse(text).unwrap();
    let classes = triples(&doc);
    let mut edits = strip_gains(text, &doc);
    let mut inherited: HashMap<roxmltree::NodeId, Option<String>> = HashMap::new();
    for b in worldbody(&doc)
        .descendants()
        .filter(|n| n.has_tag_name("body"))
    {
        let from_parent = b
            .parent()
            .and_then(|p| inherited.get(&p.id()).cloned())
            .flatten();
        let own: Vec<Triple> = b
            .children()
            .filter(|n| n.has_tag_name("joint"))
            .map(triple)
            .collect();
        let mut mine = from_parent.clone();
        if let Some(t) = own.first() {
            assert!(own.iter().all(|u| u == t), "one gain triple per body");
            let c = class_of(&classes, t).to_string();
            if from_parent.as_deref() != Some(&c) {
                edits.push(add_attr(b, "childclass", &c));
                mine = Some(c);
            }
        }
        inherited.insert(b.id(), mine);
    }
    edits.push(into_top_default(text, &doc, &class_defaults(&classes)));
    apply(text, edits)
}

/// (c) Nested classes: armature in the outer class (with a decoy stiffness
/// the innermost class overrides), damping in the middle one, stiffness in
/// the innermost, which the joints name; `type="hinge"` left to the
/// top-level class.
fn by_nested_classes(text: &str) -> String {
    let doc = roxmltree::Document::parse(text).unwrap();
    let classes = triples(&doc);
    let mut edits = strip_gains(text, &doc);
    let name = |t: &Triple, depth: usize| {
        let i = classes.iter().position(|(u, _)| u == t).unwrap();
        ["arm", "damp", "kp"][..=depth]
            .iter()
            .map(|p| format!("{p}{i}"))
            .collect::<Vec<_>>()
            .join("-")
    };
    for j in joints(&doc) {
        edits.push(add_attr(j, "class", &name(&triple(j), 2)));
        // the top-level class makes joints hinges
        edits.push(remove_attr(text, j, "type"));
    }
    let defs: String = classes
        .iter()
        .map(|(t, _)| {
            format!(
                "<default class=\"{}\"><joint armature=\"{}\" stiffness=\"1\"/>\
                 <default class=\"{}\"><joint damping=\"{}\"/>\
                 <default class=\"{}\"><joint stiffness=\"{}\"/></default>\
                 </default></default>\n",
                name(t, 0),
                t[2],
                name(t, 1),
                t[1],
                name(t, 2),
                t[0]
            )
        })
        .collect();
    edits.push(into_top_default(text, &doc, &defs));
    apply(text, edits)
}

/// Geom attributes from classes: `type="capsule"` dropped (the top-level
/// class sets it), each explicit density moved into a class named by
/// `class=`; `density=""` stays on its geoms.
fn geoms_by_class(text: &str) -> String {
    let doc = roxmltree::Document::parse(text).unwrap();
    let mut edits = Vec::new();
    let mut densities: Vec<String> = Vec::new();
    for g in worldbody(&doc)
        .descendants()
        .filter(|n| n.has_tag_name("geom") && n.parent().is_some_and(|p| p.has_tag_name("body")))
    {
        if g.attribute("type") == Some("capsule") {
            edits.push(remove_attr(text, g, "type"));
        }
        match g.attribute("density") {
            Some(d) if !d.trim().is_empty() => {
                let i = match densities.iter().position(|e| e == d) {
                    Some(i) => i,
                    None => {
                        densities.push(d.to_string());
                        densities.len() - 1
                    }
                };
                edits.push(remove_attr(text, g, "density"));
                edits.push(add_attr(g, "class", &format!("rho{i}")));
            }
            _ => {}
        }
    }
    let defs: String = densities
        .iter()
        .enumerate()
        .map(|(i, d)| format!("<default class=\"rho{i}\"><geom density=\"{d}\"/></default>\n"))
        .collect();
    edits.push(into_top_default(text, &doc, &defs));
    apply(text, edits)
}

/// Remove every `class=` attribute (the control: without its classes a
/// variant must read differently).
fn without_class_refs(text: &str) -> String {
    let doc = roxmltree::Document::parse(text).unwrap();
    let edits = doc
        .descendants()
        .filter(|n| n.is_element() && !n.has_tag_name("default"))
        .flat_map(|n| {
            ["class", "childclass"]
                .into_iter()
                .filter(move |a| n.attribute(*a).is_some())
                .map(move |a| remove_attr(text, n, a))
        })
        .collect();
    apply(text, edits)
}

fn hinge_count(m: &Model) -> usize {
    m.bodies.iter().map(|b| b.hinges.len()).sum()
}

/// A digest of every field of the model (floats by their bits).
fn fingerprint(m: &Model) -> String {
    let mut h = Sha256::new();
    let f = |h: &mut Sha256, v: &[f64]| {
        h.update((v.len() as u64).to_le_bytes());
        for x in v {
            h.update(x.to_bits().to_le_bytes());
        }
    };
    for b in &m.bodies {
        h.update(b.name.as_bytes());
        h.update([0]);
        h.update(format!("{:?}", b.parent).as_bytes());
        f(&mut h, &b.pos);
        for j in &b.hinges {
            h.update(j.name.as_bytes());
            h.update([0]);
            f(&mut h, &j.axis);
            f(&mut h, &[j.stiffness, j.damping, j.armature]);
        }
        h.update(b"geoms");
        for g in &b.geoms {
            h.update(g.kind.as_bytes());
            h.update([0]);
            f(&mut h, &g.size);
            f(&mut h, g.fromto.as_ref().map_or(&[][..], |v| &v[..]));
            f(&mut h, &g.pos);
            f(&mut h, g.quat.as_ref().map_or(&[][..], |v| &v[..]));
            f(&mut h, g.density.as_slice());
        }
        h.update(b"end");
    }
    hex::encode(h.finalize())
}

#[test]
fn shipped_files_read_as_before_the_default_classes_were_applied() {
    // Fingerprints of the models read by the reader before default classes
    // (commit b789b1d); the new reader gives field for field the same.
    for (file, bodies, hinges, digest) in [
        (
            HUMANOID,
            53,
            156,
            "bfac4acc6b7e26b1a9a76c06d3df9a9c5b7107770408edf37385705fd65595cc",
        ),
        (
            PARAHOME,
            61,
            180,
            "40d0a49afbaa53c4ac3a6ad28b468515a3b869270e9516b5d9c3e2ccd7920235",
        ),
    ] {
        let m = parse(&shipped(file));
        assert_eq!(
            (m.bodies.len(), hinge_count(&m)),
            (bodies, hinges),
            "{file}"
        );
        assert_eq!(fingerprint(&m), digest, "{file}");
    }
    let m = parse(&shipped(HUMANOID));
    let knee = &m.bodies[2];
    assert_eq!(knee.name, "L_Knee");
    let h = &knee.hinges[0];
    assert_eq!((h.stiffness, h.damping, h.armature), (500.0, 50.0, 0.02));
    assert_eq!(knee.geoms[0].kind, "capsule");
    assert_eq!(knee.geoms[0].size, vec![0.0533]);
    assert_eq!(knee.geoms[0].density, Some(1234.567901));
    let ankle = &m.bodies[3];
    assert_eq!(ankle.geoms[0].kind, "box");
    assert_eq!(ankle.geoms[0].density, None, "density=\"\" reads as unset");
    assert_eq!(ankle.geoms[0].quat, Some([1.0, 0.0, 0.0, 0.0]));
}

fn check_variant(file: &str, build: fn(&str) -> String) {
    let text = shipped(file);
    let original = parse(&text);
    let variant = build(&text);
    assert_ne!(variant, text);
    assert_gains_moved(&variant);
    assert_eq!(parse(&variant), original, "{file}");
    // control: the classes are what carries the gains
    let bare = parse(&without_class_refs(&variant));
    assert_ne!(
        bare, original,
        "{file}: the variant does not depend on its classes"
    );
    let j = &bare.bodies[1].hinges[0];
    assert_eq!(
        (j.stiffness, j.damping, j.armature),
        (5.0, 0.1, 0.007),
        "{file}: without classes the top-level class's gains apply"
    );
}

#[test]
fn joint_gains_in_default_classes_named_by_class_read_the_same() {
    for file in [HUMANOID, PARAHOME] {
        check_variant(file, by_class);
        let v = by_class(&shipped(file));
        let doc = roxmltree::Document::parse(&v).unwrap();
        assert!(joints(&doc).iter().all(|j| j.attribute("class").is_some()));
    }
}

#[test]
fn joint_gains_through_childclass_on_bodies_read_the_same() {
    for file in [HUMANOID, PARAHOME] {
        check_variant(file, by_childclass);
    }
    // the humanoid variant really uses inheritance and nested overrides
    let v = by_childclass(&shipped(HUMANOID));
    let doc = roxmltree::Document::parse(&v).unwrap();
    let bodies: Vec<_> = worldbody(&doc)
        .descendants()
        .filter(|n| n.has_tag_name("body"))
        .collect();
    let with = bodies
        .iter()
        .filter(|b| b.attribute("childclass").is_some())
        .count();
    assert!(
        with > 1 && with < bodies.len() - 1,
        "{with} of {}",
        bodies.len()
    );
    assert!(bodies.iter().any(|b| b.attribute("childclass").is_some()
        && b.ancestors()
            .skip(1)
            .any(|a| a.attribute("childclass").is_some())));
}

#[test]
fn joint_gains_in_nested_default_classes_read_the_same() {
    for file in [HUMANOID, PARAHOME] {
        check_variant(file, by_nested_classes);
    }
}

#[test]
fn geom_type_and_density_from_default_classes_read_the_same() {
    for file in [HUMANOID, PARAHOME] {
        let text = shipped(file);
        let v = geoms_by_class(&text);
        assert!(
            !v.contains("type=\"capsule\" contype"),
            "{file}: types not moved"
        );
        assert!(v.contains("class=\"rho0\""));
        assert_eq!(parse(&v), parse(&text), "{file}");
        assert_ne!(parse(&without_class_refs(&v)), parse(&text), "{file}");
    }
}

/// Set (or with `None` remove) attribute `attr` of the `index`-th `<tag>`
/// child of body `body` (`tag` "body": the body itself).
fn edit(
    text: &str,
    body: &str,
    tag: &str,
    index: usize,
    attr: &str,
    value: Option<&str>,
) -> String {
    let doc = roxmltree::Document::parse(text).unwrap();
    let b = doc
        .descendants()
        .find(|n| n.has_tag_name("body") && n.attribute("name") == Some(body))
        .unwrap_or_else(|| panic!("no body {body}"));
    let node = if tag == "body" {
        b
    } else {
        b.children()
            .filter(|n| n.has_tag_name(tag))
            .nth(index)
            .unwrap_or_else(|| panic!("body {body} has no <{tag}> {index}"))
    };
    let mut edits = Vec::new();
    if node.attribute(attr).is_some() {
        edits.push(remove_attr(text, node, attr));
    }
    if let Some(v) = value {
        edits.push(add_attr(node, attr, v));
    }
    apply(text, edits)
}

/// (body, element, index, attribute, value, words the error must hold).
type Case = (
    &'static str,
    &'static str,
    usize,
    &'static str,
    Option<&'static str>,
    &'static [&'static str],
);

#[test]
fn invalid_geometry_masses_and_rotations_are_refused_naming_the_body() {
    let text = shipped(HUMANOID);
    // (body, element, index, attribute, value, words the error must hold)
    let cases: &[Case] = &[
        (
            "L_Knee",
            "geom",
            0,
            "size",
            Some("nan"),
            &["geom 0", "size", "finite"],
        ),
        ("L_Knee", "geom", 0, "size", None, &["geom 0", "radius"]),
        (
            "L_Knee",
            "geom",
            0,
            "size",
            Some("-0.05"),
            &["geom 0", "positive"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "size",
            Some("0"),
            &["geom 0", "positive"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "size",
            Some("0.05 0.1 0.1 0.1"),
            &["geom 0", "at most 3"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "density",
            Some("0"),
            &["geom 0", "density"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "density",
            Some("-1"),
            &["geom 0", "density"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "density",
            Some("inf"),
            &["geom 0", "density"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "fromto",
            Some("0 0 0 0 0 0"),
            &["geom 0", "fromto"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "fromto",
            Some("0 0 0 nan 0 1"),
            &["geom 0", "fromto"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "pos",
            Some("0 0.1 0"),
            &["geom 0", "pos", "fromto"],
        ),
        (
            "L_Knee",
            "geom",
            0,
            "type",
            Some("capsul"),
            &["geom 0", "capsul"],
        ),
        ("L_Knee", "geom", 0, "mass", Some("2"), &["geom 0", "mass"]),
        (
            "L_Knee",
            "geom",
            0,
            "class",
            Some("nope"),
            &["geom 0", "nope"],
        ),
        (
            "L_Ankle",
            "geom",
            0,
            "quat",
            Some("0 0 0 0"),
            &["geom 0", "quat"],
        ),
        (
            "L_Ankle",
            "geom",
            0,
            "quat",
            Some("1 0 nan 0"),
            &["geom 0", "quat"],
        ),
        (
            "L_Ankle",
            "geom",
            0,
            "size",
            Some("0.0498 0.0464"),
            &["geom 0", "box"],
        ),
        (
            "L_Ankle",
            "geom",
            0,
            "euler",
            Some("0 0 90"),
            &["geom 0", "euler"],
        ),
        (
            "L_Ankle",
            "geom",
            0,
            "pos",
            Some("0 inf 0"),
            &["geom 0", "pos"],
        ),
        (
            "Pelvis",
            "geom",
            0,
            "size",
            Some("0"),
            &["geom 0", "radius"],
        ),
        (
            "Pelvis",
            "geom",
            0,
            "fromto",
            Some("0 0 0 0 0 1"),
            &["geom 0", "fromto"],
        ),
        (
            "L_Knee",
            "joint",
            0,
            "class",
            Some("nope"),
            &["L_Knee_x", "nope"],
        ),
        (
            "L_Knee",
            "joint",
            1,
            "stiffness",
            Some("-500"),
            &["L_Knee_y", "stiffness"],
        ),
        (
            "L_Knee",
            "joint",
            1,
            "damping",
            Some("nan"),
            &["L_Knee_y", "damping"],
        ),
        (
            "L_Knee",
            "joint",
            1,
            "armature",
            Some("-0.02"),
            &["L_Knee_y", "armature"],
        ),
        (
            "L_Knee",
            "joint",
            2,
            "axis",
            Some("0 0 0"),
            &["L_Knee_z", "axis"],
        ),
        (
            "L_Knee",
            "joint",
            2,
            "axis",
            Some("0 0 inf"),
            &["L_Knee_z", "axis"],
        ),
        (
            "L_Knee",
            "joint",
            2,
            "type",
            Some("hing"),
            &["L_Knee_z", "hing"],
        ),
        (
            "L_Knee",
            "body",
            0,
            "childclass",
            Some("nope"),
            &["childclass", "nope"],
        ),
        ("L_Knee", "body", 0, "pos", Some("0 nan 0"), &["pos"]),
        ("L_Knee", "body", 0, "euler", Some("0 0 90"), &["euler"]),
    ];
    for &(body, tag, index, attr, value, words) in cases {
        let v = edit(&text, body, tag, index, attr, value);
        assert_ne!(v, text);
        let e = parse_err(&v);
        let case = format!("{body} <{tag}> {index} {attr}={value:?}");
        assert!(e.contains(&format!("body `{body}`")), "{case}: {e}");
        for w in words {
            assert!(e.contains(w), "{case}: `{w}` missing from: {e}");
        }
    }
}

#[test]
fn empty_density_stays_the_default_density() {
    let text = shipped(HUMANOID);
    let v = edit(&text, "L_Knee", "geom", 0, "density", Some(""));
    let m = parse(&v);
    assert_eq!(m.bodies[2].name, "L_Knee");
    assert_eq!(m.bodies[2].geoms[0].density, None);
    // a class's density fills in for the empty attribute
    let doc = roxmltree::Document::parse(&v).unwrap();
    let v2 = apply(
        &v,
        vec![into_top_default(
            &v,
            &doc,
            "<default class=\"heavy\"><geom density=\"700\"/></default>",
        )],
    );
    let v2 = edit(&v2, "L_Knee", "geom", 0, "class", Some("heavy"));
    assert_eq!(parse(&v2).bodies[2].geoms[0].density, Some(700.0));
}

/// `stages/scale_kp.py DATA_ROOT OUT FACTOR arms|rest` (the per-joint
/// stiffness A/Bs of docs/training.md, "A stiffer drive on some joints"):
/// read back by the trainer's own reader, the copy's humanoid differs from
/// the shipped one only in the kp of the chosen joints, times the factor;
/// `arms` is the trainer's `JointSet::Arms` and `rest` its complement. A
/// second run into the same folder is refused, leaving it as it was, and
/// so is a factor of 0.
#[test]
fn scale_kp_stiffens_only_the_chosen_joints() {
    use skillaug::rl::humanoid::JointSet;
    let root = common::data_root();
    let shipped = Model::load(&root.join("assets/mjcf").join(HUMANOID)).unwrap();
    let arms = JointSet::Arms.mask(&shipped);
    let dir = tempfile::tempdir().unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("stages/scale_kp.py");
    let scale = |out: &Path, factor: &str, which: &str| {
        Command::new("python3")
            .arg(&script)
            .arg(&root)
            .arg(out)
            .arg(factor)
            .arg(which)
            .output()
            .expect("python3 runs")
    };
    // A factor that is no positive finite number is refused, naming it,
    // and nothing is written.
    let bad = dir.path().join("bad");
    let refused = scale(&bad, "0", "arms");
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("FACTOR '0'"));
    assert!(!bad.exists());
    for which in ["arms", "rest"] {
        let out = dir.path().join(which);
        let run = || scale(&out, "4", which);
        let first = run();
        assert!(
            first.status.success(),
            "{which}: {}",
            String::from_utf8_lossy(&first.stderr)
        );
        let model = Model::load(&out.join("assets/mjcf").join(HUMANOID)).unwrap();
        assert_eq!(model.names(), shipped.names());
        let mut scaled = 0;
        for (j, (b, s)) in model.bodies.iter().zip(&shipped.bodies).enumerate() {
            assert_eq!(b.geoms, s.geoms, "{}", b.name);
            assert_eq!(b.pos, s.pos, "{}", b.name);
            assert_eq!(b.hinges.len(), s.hinges.len(), "{}", b.name);
            let chosen = j > 0 && (arms[j - 1] == (which == "arms"));
            for (h, hs) in b.hinges.iter().zip(&s.hinges) {
                let kp = if chosen {
                    4.0 * hs.stiffness
                } else {
                    hs.stiffness
                };
                assert_eq!(h.stiffness, kp, "{which}: {}", h.name);
                assert_eq!((h.damping, h.armature), (hs.damping, hs.armature));
                scaled += chosen as usize;
            }
        }
        // BallPlay: 36 of the 52 joints are the arms', three hinges each.
        assert_eq!(scaled, if which == "arms" { 108 } else { 48 });
        // The clips are the shipped ones, through links.
        assert!(out.join("ballplay").exists());
        let before = std::fs::read(out.join("assets/mjcf").join(HUMANOID)).unwrap();
        let again = run();
        assert!(!again.status.success());
        assert!(
            String::from_utf8_lossy(&again.stderr).contains("already exists"),
            "{}",
            String::from_utf8_lossy(&again.stderr)
        );
        assert_eq!(
            std::fs::read(out.join("assets/mjcf").join(HUMANOID)).unwrap(),
            before
        );
    }
}
