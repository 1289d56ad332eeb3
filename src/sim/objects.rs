//! The objects the humanoid interacts with (docs/simulation.md; reference code:
//! Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/humanoid_object_task.py`,
//! `skillmimic/data/assets/urdf/ball.urdf`, `skillmimic/data/assets/obj/*.urdf`
//! and the configs under `skillmimic/data/cfg/`).
//!
//! | object | collision shape | density kg/m^3 | restitution | friction |
//! |---|---|---|---|---|
//! | ball | sphere r = 0.12 m (`ball.urdf`) | 1000 (7.24 kg) | 0.81 | 1.0 (not set in the reference; engine default) |
//! | kettle | convex decomposition of `kettle.obj` (V-HACD, see [`decompose`]) | 2500 | 0 | 0.9 (URDF) |
//! | pan | convex decomposition of `pan.obj` | 2500 | 0 | 0.9 |
//! | chair | the four convex hulls of `chair_collision.obj` (its groups) | 200 (the getup_chair configs) | 0 | 1e-5 (reference chair shapes) |
//! | book | box 0.24 x 0.17 x 0.03 m: the book mesh was never published; a hardback of this size is plausible | 2500 | 0 | 0.9 |
//! | cup | cylinder r = 0.04 m, height 0.10 m: the cup mesh was never published | 2500 | 0 | 0.9 |
//!
//! Densities and restitution follow the reference's `*_simpara` configs
//! (object density `ballDensity` 2500, restitution 0). Meshes are read with a
//! small OBJ reader of our own (vertices and faces only; no OBJ crate is
//! among the project's dependencies and the files use nothing else). Mesh
//! decompositions are computed once per process and shared between worlds
//! (a `SharedShape` is reference-counted).

use anyhow::{bail, Context, Result};
use rapier3d::math::{Pose, Vector};
use rapier3d::parry::transformation::vhacd::VHACDParameters;
use rapier3d::prelude::SharedShape;
use std::collections::HashMap;
use std::path::Path;
use std::sync::{Mutex, OnceLock};

/// One simulated object.
#[derive(Clone)]
pub struct ObjectSpec {
    /// Object name as the manifests write it (`ball`, `kettle`, ...).
    pub name: String,
    /// Collision shape in the object's frame (the frame of the data's object pose).
    pub shape: SharedShape,
    /// Density, kg/m^3.
    pub density: f32,
    /// Restitution.
    pub restitution: f32,
    /// Friction coefficient.
    pub friction: f32,
    /// Linear and angular velocity damping.
    pub damping: [f32; 2],
    /// How the shape was made (recorded in run manifests).
    pub source: String,
    /// Rotational inertia of a sphere shape: solid (rapier's from the
    /// density, 2/5 m r^2, as Isaac Gym gives the reference's URDF sphere)
    /// or a thin shell of the same mass (2/3 m r^2, a basketball's);
    /// ignored for other shapes ([`set_ball_inertia`]).
    pub inertia: BallInertia,
}

/// Rotational inertia of a ball (`train.ball_inertia`,
/// `check-ball.physics.ball_inertia`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BallInertia {
    /// A solid sphere: I = 2/5 m r^2 (the reference's URDF sphere, whose
    /// inertia Isaac Gym computes from its density).
    #[default]
    Solid,
    /// A thin spherical shell of the same mass: I = 2/3 m r^2, as a
    /// basketball's. A ball that skids on the floor and leaves it rolling
    /// keeps 3/5 of its horizontal speed instead of 5/7.
    Shell,
}

impl ObjectSpec {
    /// Mass, kg, and the principal moment of inertia, kg m^2, of a sphere
    /// object under its [`ObjectSpec::inertia`]; `None` for other shapes
    /// (whose mass properties follow from their density).
    pub fn sphere_mass_properties(&self) -> Option<(f32, f32)> {
        let r = self.shape.as_ball()?.radius;
        let m = self.density * 4.0 / 3.0 * std::f32::consts::PI * r.powi(3);
        let k = match self.inertia {
            BallInertia::Solid => 0.4,
            BallInertia::Shell => 2.0 / 3.0,
        };
        Some((m, k * m * r * r))
    }
}

impl std::fmt::Debug for ObjectSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObjectSpec")
            .field("name", &self.name)
            .field("density", &self.density)
            .field("source", &self.source)
            .field("inertia", &self.inertia)
            .finish()
    }
}

/// Radius of the basketball, m.
pub const BALL_RADIUS: f32 = 0.12;

impl ObjectSpec {
    /// The basketball.
    pub fn ball() -> ObjectSpec {
        ObjectSpec {
            name: "ball".into(),
            shape: SharedShape::ball(BALL_RADIUS),
            density: 1000.0,
            restitution: 0.81,
            friction: 1.0,
            damping: [0.01, 0.01],
            source: "sphere r=0.12 (ball.urdf)".into(),
            inertia: BallInertia::Solid,
        }
    }

    /// An object by manifest name; meshes are read from `assets/obj` under
    /// the data root.
    pub fn load(name: &str, data_root: &Path) -> Result<ObjectSpec> {
        let obj = data_root.join("assets/obj");
        let (shape, density, friction, source) = match name {
            "ball" => return Ok(ObjectSpec::ball()),
            "book" => (
                SharedShape::cuboid(0.12, 0.085, 0.015),
                2500.0,
                0.9,
                "box 0.24x0.17x0.03 (no published mesh)".to_string(),
            ),
            "cup" => (
                SharedShape::cylinder(0.05, 0.04),
                2500.0,
                0.9,
                "cylinder r=0.04 h=0.10 (no published mesh)".to_string(),
            ),
            "kettle" | "pan" => {
                let path = obj.join(format!("{name}.obj"));
                (
                    cached(&path, |p| {
                        let m = read_obj(p)?;
                        Ok(decompose(&m.vertices, &m.triangles))
                    })?,
                    2500.0,
                    0.9,
                    format!("V-HACD decomposition of {name}.obj"),
                )
            }
            "chair" => {
                let path = obj.join("chair_collision.obj");
                (
                    cached(&path, |p| {
                        let m = read_obj(p)?;
                        group_hulls(&m).with_context(|| p.display().to_string())
                    })?,
                    200.0,
                    1e-5,
                    "convex hulls of the groups of chair_collision.obj".to_string(),
                )
            }
            other => bail!("no simulated object is defined for `{other}` (known: ball, book, chair, cup, kettle, pan)"),
        };
        Ok(ObjectSpec {
            name: name.to_string(),
            shape,
            density,
            restitution: 0.0,
            friction,
            damping: [0.01, 0.01],
            source,
            inertia: BallInertia::Solid,
        })
    }
}

/// The objects of a clip, by manifest names, in order.
pub fn load_all(names: &[String], data_root: &Path) -> Result<Vec<ObjectSpec>> {
    names
        .iter()
        .map(|n| ObjectSpec::load(n, data_root))
        .collect()
}

/// Replace every object's density by `density`, kg/m^3, when one is given
/// (`train.object_density`, `check-ball.physics.object_density`); `None`
/// keeps each object's own. The mass follows from the shape's volume when
/// a world is built.
pub fn set_density(objects: &mut [ObjectSpec], density: Option<f32>) {
    if let Some(d) = density {
        for o in objects {
            o.density = d;
        }
    }
}

/// Set every object's angular velocity damping to `damping`, 1/s
/// (rapier's `angular_damping`: the angular velocity is scaled by
/// 1 / (1 + dt damping) at every physics step of dt seconds), in place of
/// its own (0.01, the reference's `humanoid_object_task.py`); `None`
/// keeps each object's own (`train.object_angular_damping`,
/// `check-ball.physics.object_angular_damping`).
pub fn set_angular_damping(objects: &mut [ObjectSpec], damping: Option<f32>) {
    if let Some(d) = damping {
        for o in objects {
            o.damping[1] = d;
        }
    }
}

/// Give every sphere object the rotational inertia `inertia`
/// (`train.ball_inertia`, `check-ball.physics.ball_inertia`); its mass
/// stays the density's.
pub fn set_ball_inertia(objects: &mut [ObjectSpec], inertia: BallInertia) {
    for o in objects {
        o.inertia = inertia;
    }
}

/// Shapes built from files, once per process.
fn cached(path: &Path, build: impl FnOnce(&Path) -> Result<SharedShape>) -> Result<SharedShape> {
    static CACHE: OnceLock<Mutex<HashMap<std::path::PathBuf, SharedShape>>> = OnceLock::new();
    let cache = CACHE.get_or_init(|| Mutex::new(HashMap::new()));
    if let Some(s) = cache.lock().unwrap().get(path) {
        return Ok(s.clone());
    }
    let s = build(path)?;
    cache.lock().unwrap().insert(path.to_path_buf(), s.clone());
    Ok(s)
}

/// Decompose a triangle mesh into convex parts. V-HACD with a voxel
/// resolution of 64 and at most 16 hulls: the reference asks PhysX for
/// resolution 1e4-1e6 and 10-40 hulls, which here takes minutes per mesh
/// for no visible gain at hand scale.
pub fn decompose(vertices: &[Vector], triangles: &[[u32; 3]]) -> SharedShape {
    let params = VHACDParameters {
        resolution: 64,
        max_convex_hulls: 16,
        ..VHACDParameters::default()
    };
    SharedShape::convex_decomposition_with_params(vertices, triangles, &params)
}

/// A mesh read from an OBJ file: vertices, triangles and the first
/// triangle of each group (`g`/`o` line).
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<Vector>,
    /// Triangles (polygons are fanned).
    pub triangles: Vec<[u32; 3]>,
    /// Vertex ranges of each group, `[start, end)` into `vertices`.
    pub groups: Vec<(usize, usize)>,
}

/// Read the vertices and faces of an OBJ file.
pub fn read_obj(path: &Path) -> Result<Mesh> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the object mesh {}", path.display()))?;
    parse_obj(&text).with_context(|| path.display().to_string())
}

/// Parse OBJ text (see [`read_obj`]).
pub fn parse_obj(text: &str) -> Result<Mesh> {
    let mut m = Mesh::default();
    let mut group_start = 0usize;
    for (n, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let c: Vec<f32> = it
                    .take(3)
                    .map(|t| t.parse::<f32>())
                    .collect::<Result<_, _>>()
                    .with_context(|| format!("line {}: bad vertex", n + 1))?;
                if c.len() != 3 {
                    bail!("line {}: a vertex needs three coordinates", n + 1);
                }
                m.vertices.push(Vector::new(c[0], c[1], c[2]));
            }
            Some("f") => {
                let idx: Vec<u32> = it
                    .map(|t| {
                        let i: i64 = t.split('/').next().unwrap_or("").parse()?;
                        let nv = m.vertices.len() as i64;
                        let i = if i < 0 { nv + i } else { i - 1 };
                        if i < 0 || i >= nv {
                            bail!("vertex index {t} out of range");
                        }
                        Ok(i as u32)
                    })
                    .collect::<Result<_>>()
                    .with_context(|| format!("line {}: bad face", n + 1))?;
                for k in 1..idx.len().saturating_sub(1) {
                    m.triangles.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
            Some("g") | Some("o") => {
                if m.vertices.len() > group_start {
                    m.groups.push((group_start, m.vertices.len()));
                }
                group_start = m.vertices.len();
            }
            _ => {}
        }
    }
    if m.vertices.len() > group_start {
        m.groups.push((group_start, m.vertices.len()));
    }
    if m.vertices.is_empty() {
        bail!("no vertices");
    }
    Ok(m)
}

/// A compound of the convex hulls of each group's vertices.
fn group_hulls(m: &Mesh) -> Result<SharedShape> {
    let mut parts = Vec::new();
    for (k, &(a, b)) in m.groups.iter().enumerate() {
        let hull = SharedShape::convex_hull(&m.vertices[a..b])
            .with_context(|| format!("group {k} has no convex hull"))?;
        parts.push((Pose::IDENTITY, hull));
    }
    Ok(SharedShape::compound(parts))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_reader_fans_polygons_and_splits_groups() {
        let text = "g a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1/1/1 2/2/2 3/3/3 4/4/4\ng b\nv 0 0 1\nv 1 0 1\nv 0 1 1\nf -3 -2 -1\n";
        let m = parse_obj(text).unwrap();
        assert_eq!(m.vertices.len(), 7);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3], [4, 5, 6]]);
        assert_eq!(m.groups, vec![(0, 4), (4, 7)]);
    }

    #[test]
    fn obj_reader_names_the_bad_line() {
        let e = parse_obj("v 0 0 0\nf 1 2 9\n").unwrap_err();
        assert!(format!("{e:#}").contains("line 2"), "{e:#}");
    }
}
