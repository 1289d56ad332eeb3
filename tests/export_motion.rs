//! `skillaug export --bvh/--gltf` on the real clips (docs/export.md), the files
//! read back by independent readers: the `bvh` and `pygltflib` Python
//! packages (forward kinematics in numpy, against an exp-map FK of the MJCF
//! written here in Python from the stored root and joint values), a
//! structural walk of the GLB written here, and the Khronos glTF validator
//! where node has it.
//!
//! Why not the stored `body_pos`: BallPlay's stored body positions come from
//! the capture skeleton, whose limb lengths differ from the MJCF model's by
//! up to 14 cm (`skillaug check-fk --dataset ballplay`), ParaHome's by up to
//! 1.7 cm; an exported file can only reproduce the model's kinematics. The
//! scripts print that gap beside the 1-mm check.

mod common;

use common::*;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A Python 3 with the readers (`.ci/run` pip-installs them).
fn python() -> PathBuf {
    python_with(&["numpy", "pyarrow", "bvh", "pygltflib"])
}

/// Run a Python `script` with `args`; require success and return stdout.
fn run_python(script: &str, args: &[&str]) -> String {
    let o = Command::new(python())
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "python check failed:\n{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    eprint!("{out}");
    out
}

/// The MJCF model of a skeleton in the shipped data.
fn mjcf(name: &str) -> String {
    data_root()
        .join(format!("assets/mjcf/{name}.xml"))
        .to_string_lossy()
        .into_owned()
}

/// The largest error the script reported (`max_error_mm X`).
fn max_error_mm(out: &str) -> f64 {
    out.lines()
        .find_map(|l| l.strip_prefix("max_error_mm "))
        .and_then(|l| l.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .expect("a max_error_mm line")
}

/// Shared Python: the MJCF bodies (document order: name, parent, pos), the
/// frames table, and exp-map forward kinematics of a stored frame.
const PY_FK: &str = r#"
import sys, xml.etree.ElementTree as ET
import numpy as np, pyarrow.parquet as pq

def mjcf_bodies(path):
    out = []
    def walk(e, parent):
        for b in e.findall("body"):
            out.append((b.get("name"), parent, [float(v) for v in b.get("pos", "0 0 0").split()]))
            walk(b, len(out) - 1)
    walk(ET.parse(path).getroot().find("worldbody"), -1)
    return out

def quat_m(q):
    """Rotation matrices [..., 3, 3] of quaternions [..., 4] (x, y, z, w)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)

def expmap_m(e):
    """Rodrigues' formula; below 1e-5 rad the identity (the simulator's rule)."""
    e = np.array(e, float)
    a = np.linalg.norm(e)
    if a < 1e-5:
        return np.eye(3)
    k = e / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * (K @ K)

def fk(bodies, frames, i):
    """World body positions [B, 3] of frames row i: child rot = parent rot *
    expmap(joint), child pos = parent pos + parent rot * MJCF pos."""
    jr = frames["joint_rot"][i]
    R = [None] * len(bodies)
    P = [None] * len(bodies)
    for j, (_, p, pos) in enumerate(bodies):
        if p < 0:
            R[j] = quat_m(frames["root_rot"][i])
            P[j] = np.array(frames["root_pos"][i], float)
        else:
            R[j] = R[p] @ expmap_m(jr[3 * j - 3:3 * j])
            P[j] = P[p] + R[p] @ np.array(pos)
    return np.array(P)

def read_frames(run):
    cols = ["clip_id", "frame", "valid", "body_pos", "root_pos", "root_rot", "joint_rot", "obj_pos"]
    frames = pq.read_table(run + "/frames.parquet", columns=cols).to_pydict()
    clips = {r["clip_id"]: r for r in pq.read_table(run + "/clips.parquet").to_pylist()}
    return frames, clips

def clip_rows(frames, clip):
    rows = [i for i, c in enumerate(frames["clip_id"]) if c == clip]
    return sorted(rows, key=lambda i: frames["frame"][i])

# files are y up: (x, y, z)_file = (x, z, -y)_simulator
TO_Z_UP = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)
"#;

/// BVH check. argv: run_dir mjcf (bvh_file clip_id metres_per_unit)...
const PY_BVH: &str = r#"
from bvh import Bvh

run, bodies = sys.argv[1], mjcf_bodies(sys.argv[2])
frames, clips = read_frames(run)
jobs = sys.argv[3:]

def rot(axis, deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    m = np.tile(np.eye(3), (len(a), 1, 1))
    i, j = {"X": (1, 2), "Y": (2, 0), "Z": (0, 1)}[axis]
    m[:, i, i] = c
    m[:, j, j] = c
    m[:, i, j] = -s
    m[:, j, i] = s
    return m

worst = 0.0
for k in range(0, len(jobs), 3):
    path, clip, unit = jobs[k], int(jobs[k + 1]), float(jobs[k + 2])
    with open(path) as f:
        m = Bvh(f.read())
    names = m.get_joints_names()
    nb = len(names)
    assert names == [b[0] for b in bodies], names[:5]
    assert [m.joint_parent_index(n) for n in names] == [b[1] for b in bodies]
    for n, (_, p, pos) in zip(names, bodies):
        off = np.array(m.joint_offset(n)) * unit
        want = np.zeros(3) if p < 0 else np.array(pos)
        assert np.abs(off - want).max() < 1e-6, (n, off, want)
        want_ch = 6 if p < 0 else 3
        assert len(m.joint_channels(n)) == want_ch, m.joint_channels(n)
    leaves = [n for j, n in enumerate(names) if not any(b[1] == j for b in bodies)]
    assert len(m.search("End")) == len(leaves), (len(m.search("End")), len(leaves))
    assert abs(m.frame_time - 1.0 / clips[clip]["fps"]) < 1e-8, m.frame_time
    data = np.array(m.frames, dtype=float)
    rows = clip_rows(frames, clip)
    n = m.nframes
    assert n == len(rows) and data.shape == (n, 6 + 3 * (nb - 1)), (n, len(rows), data.shape)
    # forward kinematics of the file: T(offset) * R(channels in order)
    R = [None] * nb
    P = [None] * nb
    col = 0
    for j, name in enumerate(names):
        r = np.tile(np.eye(3), (n, 1, 1))
        t = np.zeros((n, 3))
        for c in m.joint_channels(name):
            v = data[:, col]
            col += 1
            if c.endswith("position"):
                t[:, "XYZ".index(c[0])] = v * unit
            else:
                r = r @ rot(c[0], v)
        off = np.array(m.joint_offset(name)) * unit
        p = bodies[j][1]
        if p < 0:
            R[j], P[j] = r, off + t
        else:
            R[j] = R[p] @ r
            P[j] = P[p] + np.einsum("nij,j->ni", R[p], off)
    got = np.stack(P, 1) @ TO_Z_UP.T
    want = np.stack([fk(bodies, frames, i) for i in rows])
    stored = np.array([frames["body_pos"][i] for i in rows]).reshape(n, nb, 3)
    valid = np.array([frames["valid"][i] for i in rows])
    err = np.abs(got - want)[valid].max() * 1000
    gap = np.linalg.norm(got - stored, axis=-1)[valid].max() * 1000
    worst = max(worst, err)
    print(f"bvh clip {clip} ({clips[clip]['name']}, unit {unit:g} m): {n} frames, {nb} joints, "
          f"max error {err:.4f} mm (stored body_pos differs by up to {gap:.1f} mm)")
    assert err < 1.0, (path, err)
print(f"max_error_mm {worst:.6f}")
"#;

/// glTF check. argv: run_dir mjcf glb clip_ids (comma-separated, in
/// animation order).
const PY_GLTF: &str = r#"
from pygltflib import GLTF2

run, bodies, glb = sys.argv[1], mjcf_bodies(sys.argv[2]), sys.argv[3]
anim_clips = [int(c) for c in sys.argv[4].split(",")]
frames, clips = read_frames(run)
nb = len(bodies)

g = GLTF2().load(glb)
blob = g.binary_blob()

def read(i):
    a = g.accessors[i]
    v = g.bufferViews[a.bufferView]
    assert v.byteStride in (None, 0)
    dt = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[a.componentType]
    w = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[a.type]
    off = (v.byteOffset or 0) + (a.byteOffset or 0)
    assert off + a.count * w * np.dtype(dt).itemsize <= (v.byteOffset or 0) + v.byteLength
    return np.frombuffer(blob, dtype=dt, count=a.count * w, offset=off).reshape(a.count, w).astype(float)

parent = {}
for i, nd in enumerate(g.nodes):
    for c in nd.children or []:
        assert c not in parent, "a node with two parents"
        parent[c] = i
char0 = g.scenes[g.scene or 0].nodes[0]
order = []
def dfs(i):
    order.append(i)
    for c in g.nodes[i].children or []:
        dfs(c)
dfs(g.nodes[char0].children[0])
assert [g.nodes[i].name for i in order] == [b[0] for b in bodies], [g.nodes[i].name for i in order][:5]
for i, (_, p, pos) in zip(order, bodies):
    if p >= 0:
        assert parent[i] == order[p]
        assert np.abs(np.array(g.nodes[i].translation) - pos).max() < 1e-6
objects = {g.nodes[i].name: i for i in g.nodes[char0].children[1:]}
assert len(g.animations) == len(anim_clips), (len(g.animations), anim_clips)
print(f"glb: {len(g.nodes)} nodes, {nb} bodies per character, objects {sorted(objects)}")

worst = worst_obj = 0.0
for anim, clip in zip(g.animations, anim_clips):
    info = clips[clip]
    rows = clip_rows(frames, clip)
    n = len(rows)
    # every node's local transform per frame: its defaults, then the channels
    N = len(g.nodes)
    T = np.zeros((N, n, 3))
    R = np.tile(np.eye(3), (N, n, 1, 1))
    S = np.ones((N, n, 3))
    for i, nd in enumerate(g.nodes):
        if nd.translation: T[i] = nd.translation
        if nd.rotation: R[i] = quat_m(nd.rotation)
        if nd.scale: S[i] = nd.scale
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        t, out = read(s.input)[:, 0], read(s.output)
        acc = g.accessors[s.input]
        assert acc.min == [float(t.min())] and acc.max == [float(t.max())], (acc.min, acc.max)
        if len(t) > 1:
            assert s.interpolation == "LINEAR" and len(t) == n and len(out) == n
            assert np.abs(t - np.arange(n) / info["fps"]).max() < 1e-5
        else:
            assert s.interpolation == "STEP" and ch.target.path == "scale"
            out = np.repeat(out, n, 0)
        node = ch.target.node
        if ch.target.path == "translation":
            T[node] = out
        elif ch.target.path == "rotation":
            assert np.abs(np.linalg.norm(out, axis=1) - 1).max() < 1e-5
            R[node] = quat_m(out)
        else:
            S[node] = out
    W = {}
    def world(i):
        if i not in W:
            m = np.tile(np.eye(4), (n, 1, 1))
            m[:, :3, :3] = R[i] * S[i][:, None, :]
            m[:, :3, 3] = T[i]
            W[i] = m if i not in parent else world(parent[i]) @ m
        return W[i]
    got = np.stack([world(i)[:, :3, 3] for i in order], 1) @ TO_Z_UP.T
    want = np.stack([fk(bodies, frames, i) for i in rows])
    stored = np.array([frames["body_pos"][i] for i in rows]).reshape(n, nb, 3)
    valid = np.array([frames["valid"][i] for i in rows])
    err = np.abs(got - want)[valid].max() * 1000
    gap = np.linalg.norm(got - stored, axis=-1)[valid].max() * 1000
    worst = max(worst, err)
    assert err < 1.0, (anim.name, err)
    line = (f"glb {anim.name}: {n} frames, max body error {err:.4f} mm "
            f"(stored body_pos differs by up to {gap:.1f} mm)")
    obj_pos = np.array([frames["obj_pos"][i] for i in rows]).reshape(n, -1, 3)
    for name, i in objects.items():
        if name in info["objects"]:
            k = info["objects"].index(name)
            assert np.all(S[i] == 1)
            e = np.abs(world(i)[:, :3, 3] @ TO_Z_UP.T - obj_pos[:, k])[valid].max() * 1000
            worst_obj = max(worst_obj, e)
            assert e < 1.0, (anim.name, name, e)
            line += f"; {name} {e:.4f} mm"
        else:
            assert np.all(S[i] == 0), (anim.name, name, "not hidden")
            line += f"; {name} hidden"
    print(line)
print(f"max_error_mm {worst:.6f} objects {worst_obj:.6f}")
"#;

/// `skillaug export --from run` with `extra` flags; returns stdout.
fn export(run: &Path, extra: &[&str]) -> String {
    let mut a = vec!["export", "--from", run.to_str().unwrap()];
    a.extend_from_slice(extra);
    ok(&a)
}

fn u32_at(b: &[u8], i: usize) -> usize {
    u32::from_le_bytes(b[i..i + 4].try_into().unwrap()) as usize
}

/// Structural walk of a GLB file (glTF 2.0 §4.4 and the schema's
/// invariants): header and chunks, every buffer view and accessor inside
/// the buffer, meshes' indices inside their vertex counts, samplers'
/// inputs increasing with min/max, rotations unit, one parent per node.
/// Returns the JSON document and the BIN chunk.
fn check_glb(bytes: &[u8]) -> (Value, Vec<u8>) {
    assert_eq!(&bytes[0..4], b"glTF");
    assert_eq!(u32_at(bytes, 4), 2, "version");
    assert_eq!(u32_at(bytes, 8), bytes.len(), "header length");
    let jlen = u32_at(bytes, 12);
    assert_eq!(&bytes[16..20], b"JSON");
    assert_eq!(jlen % 4, 0);
    let json = &bytes[20..20 + jlen];
    let doc: Value = serde_json::from_slice(json).expect("JSON chunk");
    let text = std::str::from_utf8(json).unwrap();
    assert!(
        text.len() - text.trim_end_matches(' ').len() < 4,
        "JSON padded with spaces"
    );
    assert!(text.trim_end_matches(' ').ends_with('}'));
    let b0 = 20 + jlen;
    let blen = u32_at(bytes, b0);
    assert_eq!(&bytes[b0 + 4..b0 + 8], b"BIN\0");
    assert_eq!(blen % 4, 0);
    assert_eq!(b0 + 8 + blen, bytes.len(), "BIN is the last chunk");
    let bin = bytes[b0 + 8..].to_vec();

    assert_eq!(doc["asset"]["version"], "2.0");
    let buffers = doc["buffers"].as_array().unwrap();
    assert_eq!(buffers.len(), 1);
    assert!(buffers[0].get("uri").is_none());
    let buf_len = buffers[0]["byteLength"].as_u64().unwrap() as usize;
    assert!(buf_len <= bin.len() && bin.len() - buf_len < 4);
    let views = doc["bufferViews"].as_array().unwrap();
    for v in views {
        let off = v["byteOffset"].as_u64().unwrap_or(0) as usize;
        let len = v["byteLength"].as_u64().unwrap() as usize;
        assert_eq!(off % 4, 0, "view alignment");
        assert!(off + len <= buf_len, "view out of the buffer");
        assert!(v.get("byteStride").is_none());
    }
    let accessors = doc["accessors"].as_array().unwrap();
    let floats = |i: usize| -> Vec<f32> {
        let a = &accessors[i];
        assert_eq!(a["componentType"], 5126);
        let v = &views[a["bufferView"].as_u64().unwrap() as usize];
        let off = v["byteOffset"].as_u64().unwrap_or(0) as usize
            + a["byteOffset"].as_u64().unwrap_or(0) as usize;
        let w = match a["type"].as_str().unwrap() {
            "SCALAR" => 1,
            "VEC3" => 3,
            "VEC4" => 4,
            t => panic!("type {t}"),
        };
        let n = a["count"].as_u64().unwrap() as usize * w;
        (0..n)
            .map(|k| f32::from_le_bytes(bin[off + 4 * k..off + 4 * k + 4].try_into().unwrap()))
            .collect()
    };
    for a in accessors {
        let v = &views[a["bufferView"].as_u64().unwrap() as usize];
        let comp = match a["componentType"].as_u64().unwrap() {
            5126 | 5125 => 4,
            5123 => 2,
            c => panic!("component type {c}"),
        };
        let w = match a["type"].as_str().unwrap() {
            "SCALAR" => 1,
            "VEC3" => 3,
            "VEC4" => 4,
            t => panic!("type {t}"),
        };
        let off = a["byteOffset"].as_u64().unwrap_or(0) as usize;
        let count = a["count"].as_u64().unwrap() as usize;
        assert!(count > 0);
        assert_eq!(off % comp, 0);
        assert!(
            off + count * comp * w <= v["byteLength"].as_u64().unwrap() as usize,
            "accessor out of its view"
        );
    }
    for m in doc["meshes"].as_array().unwrap() {
        for p in m["primitives"].as_array().unwrap() {
            let pos = p["attributes"]["POSITION"].as_u64().unwrap() as usize;
            let nrm = p["attributes"]["NORMAL"].as_u64().unwrap() as usize;
            let nv = accessors[pos]["count"].as_u64().unwrap();
            assert_eq!(accessors[nrm]["count"].as_u64().unwrap(), nv);
            assert!(accessors[pos].get("min").is_some() && accessors[pos].get("max").is_some());
            let ia = &accessors[p["indices"].as_u64().unwrap() as usize];
            assert_eq!(ia["count"].as_u64().unwrap() % 3, 0);
            let v = &views[ia["bufferView"].as_u64().unwrap() as usize];
            let off = v["byteOffset"].as_u64().unwrap_or(0) as usize;
            for k in 0..ia["count"].as_u64().unwrap() as usize {
                let i = match ia["componentType"].as_u64().unwrap() {
                    5123 => u16::from_le_bytes([bin[off + 2 * k], bin[off + 2 * k + 1]]) as u64,
                    5125 => u32_at(&bin, off + 4 * k) as u64,
                    c => panic!("index component type {c}"),
                };
                assert!(i < nv, "index out of range");
            }
            for n in floats(nrm).chunks(3) {
                let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                assert!((l - 1.0).abs() < 1e-5, "normal length {l}");
            }
        }
    }
    let nodes = doc["nodes"].as_array().unwrap();
    let mut parent = vec![None; nodes.len()];
    for (i, n) in nodes.iter().enumerate() {
        for c in n["children"].as_array().into_iter().flatten() {
            let c = c.as_u64().unwrap() as usize;
            assert!(parent[c].is_none(), "node {c} has two parents");
            parent[c] = Some(i);
        }
    }
    for r in doc["scenes"][0]["nodes"].as_array().unwrap() {
        assert!(parent[r.as_u64().unwrap() as usize].is_none());
    }
    for a in doc["animations"].as_array().unwrap() {
        let samplers = a["samplers"].as_array().unwrap();
        for ch in a["channels"].as_array().unwrap() {
            let s = &samplers[ch["sampler"].as_u64().unwrap() as usize];
            assert!((ch["target"]["node"].as_u64().unwrap() as usize) < nodes.len());
            let input = s["input"].as_u64().unwrap() as usize;
            let t = floats(input);
            assert!(t.windows(2).all(|w| w[1] > w[0]), "times increase");
            assert_eq!(accessors[input]["min"][0].as_f64().unwrap(), t[0] as f64);
            assert_eq!(
                accessors[input]["max"][0].as_f64().unwrap(),
                *t.last().unwrap() as f64
            );
            let out = floats(s["output"].as_u64().unwrap() as usize);
            let w = match ch["target"]["path"].as_str().unwrap() {
                "rotation" => 4,
                _ => 3,
            };
            assert_eq!(out.len(), w * t.len(), "one output per key");
            if w == 4 {
                for q in out.chunks(4) {
                    let l = q.iter().map(|x| x * x).sum::<f32>().sqrt();
                    assert!((l - 1.0).abs() < 1e-5, "rotation not unit: {l}");
                }
            }
        }
    }
    (doc, bin)
}

/// Nodes in the subtree of `root`, depth-first.
fn subtree(doc: &Value, root: usize) -> Vec<usize> {
    let mut out = vec![root];
    for c in doc["nodes"][root]["children"]
        .as_array()
        .into_iter()
        .flatten()
    {
        out.extend(subtree(doc, c.as_u64().unwrap() as usize));
    }
    out
}

#[test]
fn bvh_files_read_back_to_the_models_kinematics() {
    let (dir, run) = ingested("ballplay");
    let (cm, m) = (dir.path().join("cm"), dir.path().join("m"));
    let clips = ["0", "1", "2", "3", "4", "5"];
    let mut a = vec!["--bvh", cm.to_str().unwrap(), "-q"];
    for c in &clips {
        a.extend_from_slice(&["--clip", c]);
    }
    export(&run, &a);
    export(
        &run,
        &[
            "--clip",
            "013_018pickle_run_4",
            "--bvh",
            m.to_str().unwrap(),
            "--units",
            "m",
            "-q",
        ],
    );
    let lib = skillaug::table::load_library(&run).unwrap();
    let names: Vec<String> = lib.clips.iter().map(|c| c.name.clone()).collect();
    assert_eq!(entries(&cm), {
        let mut v: Vec<String> = names.iter().map(|n| format!("clip-{n}.bvh")).collect();
        v.sort();
        v
    });
    let mut args = vec![run.to_str().unwrap().to_string(), mjcf("mocap_humanoid")];
    for (i, n) in names.iter().enumerate() {
        args.push(
            cm.join(format!("clip-{n}.bvh"))
                .to_string_lossy()
                .into_owned(),
        );
        args.push(i.to_string());
        args.push("0.01".into());
    }
    args.push(
        m.join("clip-013_018pickle_run_4.bvh")
            .to_string_lossy()
            .into_owned(),
    );
    args.push("4".into());
    args.push("1".into());
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = run_python(&format!("{PY_FK}{PY_BVH}"), &args);
    assert!(max_error_mm(&out) < 1.0);
    assert_eq!(out.matches("bvh clip").count(), 7);

    // the text itself: channel orders, frame time, y up (the pelvis high)
    let text = std::fs::read_to_string(cm.join(format!("clip-{}.bvh", names[0]))).unwrap();
    assert!(text.starts_with("HIERARCHY\nROOT Pelvis\n{\n\tOFFSET 0.0000 0.0000 0.0000\n\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"));
    assert_eq!(
        text.matches("CHANNELS 3 Zrotation Xrotation Yrotation")
            .count(),
        52
    );
    assert!(text.contains("\nFrame Time: 0.016666667\n"));
    let first = text.split("Frame Time: 0.016666667\n").nth(1).unwrap();
    let v: Vec<f64> = first
        .lines()
        .next()
        .unwrap()
        .split(' ')
        .map(|x| x.parse().unwrap())
        .collect();
    assert_eq!(v.len(), 6 + 52 * 3);
    let want = lib.state(0, 0).unwrap().root_pos;
    assert!(
        (v[1] - 100.0 * want[2] as f64).abs() < 1e-3,
        "Y is the simulator's z, cm"
    );
    assert!(
        (v[2] + 100.0 * want[1] as f64).abs() < 1e-3,
        "Z is minus the simulator's y"
    );
}

#[test]
fn bvh_and_gltf_hold_the_last_posture_over_missing_frames() {
    let (dir, run) = ingested("ballplay");
    let from = run.to_str().unwrap();
    // STF samples with masked states: their missing reference frames are None
    sample_masked_stf(from);
    let stf = run.join("stf_samples.parquet");
    let trajs = skillaug::table::stf::read_trajectories(&stf).unwrap();
    let t = trajs
        .iter()
        .find(|t| t.steps.iter().any(|st| st.reference.is_none()))
        .expect("a trajectory with missing frames");
    let id = t.traj_id.to_string();
    let bvh = dir.path().join("b");
    let glb = dir.path().join("s.glb");
    export(
        &run,
        &[
            "--stf",
            stf.to_str().unwrap(),
            "--traj",
            &id,
            "--bvh",
            bvh.to_str().unwrap(),
            "--gltf",
            glb.to_str().unwrap(),
            "-q",
        ],
    );
    let text = std::fs::read_to_string(bvh.join(format!("stf-{id}.bvh"))).unwrap();
    let lines: Vec<&str> = text
        .split("Frame Time: ")
        .nth(1)
        .unwrap()
        .lines()
        .skip(1)
        .collect();
    assert_eq!(lines.len(), 1 + t.steps.len());
    let mut held = 0;
    for (k, st) in t.steps.iter().enumerate() {
        if st.reference.is_none() {
            assert_eq!(
                lines[k + 1],
                lines[k],
                "step {} holds the last posture",
                k + 1
            );
            held += 1;
        }
    }
    assert!(held > 0);
    let (doc, bin) = check_glb(&std::fs::read(&glb).unwrap());
    let anim = &doc["animations"][0];
    assert_eq!(
        anim["name"],
        format!("STF trajectory {id} ({})", t.start_kind)
    );
    // the root's translation keys hold too
    let root = doc["scenes"][0]["nodes"][0].as_u64().unwrap() as usize;
    let pelvis = doc["nodes"][root]["children"][0].as_u64().unwrap();
    let ch = anim["channels"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["target"]["node"] == pelvis && c["target"]["path"] == "translation")
        .unwrap();
    let out = &doc["accessors"][anim["samplers"][ch["sampler"].as_u64().unwrap() as usize]["output"]
        .as_u64()
        .unwrap() as usize];
    let off = doc["bufferViews"][out["bufferView"].as_u64().unwrap() as usize]["byteOffset"]
        .as_u64()
        .unwrap() as usize;
    let key = |k: usize| &bin[off + 12 * k..off + 12 * k + 12];
    for (k, st) in t.steps.iter().enumerate() {
        if st.reference.is_none() {
            assert_eq!(key(k + 1), key(k));
        }
    }
}

#[test]
fn gltf_of_ballplay_reads_back_to_the_models_kinematics() {
    let (dir, run) = ingested("ballplay");
    let glb = dir.path().join("all.glb");
    let mut a = vec!["--gltf", glb.to_str().unwrap(), "-q"];
    let clips = ["0", "1", "2", "3", "4", "5"];
    for c in &clips {
        a.extend_from_slice(&["--clip", c]);
    }
    export(&run, &a);
    let (doc, _) = check_glb(&std::fs::read(&glb).unwrap());
    // one character: its node, 53 bodies nested like the model, the ball
    let scene = doc["scenes"][0]["nodes"].as_array().unwrap();
    assert_eq!(scene.len(), 1);
    let top = scene[0].as_u64().unwrap() as usize;
    let kids = doc["nodes"][top]["children"].as_array().unwrap();
    assert_eq!(kids.len(), 2);
    let body_nodes = subtree(&doc, kids[0].as_u64().unwrap() as usize);
    assert_eq!(body_nodes.len(), 53);
    assert_eq!(doc["nodes"][body_nodes[0]]["name"], "Pelvis");
    assert_eq!(
        doc["nodes"][kids[1].as_u64().unwrap() as usize]["name"],
        "ball"
    );
    assert_eq!(doc["animations"].as_array().unwrap().len(), 6);
    // no scale channels: every motion has the one character and the ball
    assert!(!serde_json::to_string(&doc["animations"])
        .unwrap()
        .contains("scale"));
    let out = run_python(
        &format!("{PY_FK}{PY_GLTF}"),
        &[
            run.to_str().unwrap(),
            &mjcf("mocap_humanoid"),
            glb.to_str().unwrap(),
            &clips.join(","),
        ],
    );
    assert!(max_error_mm(&out) < 1.0);
    khronos_validator(&glb);
}

#[test]
fn gltf_of_parahome_animates_and_hides_the_objects() {
    let (dir, run) = ingested("parahome");
    let lib = skillaug::table::load_library(&run).unwrap();
    let id = |name: &str| lib.clips.iter().position(|c| c.name == name).unwrap();
    // two objects (kettle, cup), then a cup alone, then a kettle alone
    let order = [
        id("010_s6_pour_kettlecup_1650_1860"),
        id("001_s6_drink_1860_2040"),
        id("003_s10_place_kettle_2580_2680"),
    ];
    let ids: Vec<String> = order.iter().map(|i| i.to_string()).collect();
    let glb = dir.path().join("ph.glb");
    let mut a = vec!["--gltf", glb.to_str().unwrap(), "-q"];
    for c in &ids {
        a.extend_from_slice(&["--clip", c]);
    }
    export(&run, &a);
    let (doc, _) = check_glb(&std::fs::read(&glb).unwrap());
    let top = doc["scenes"][0]["nodes"][0].as_u64().unwrap() as usize;
    let kids = doc["nodes"][top]["children"].as_array().unwrap();
    let names: Vec<&str> = kids[1..]
        .iter()
        .map(|k| {
            doc["nodes"][k.as_u64().unwrap() as usize]["name"]
                .as_str()
                .unwrap()
        })
        .collect();
    assert_eq!(names, ["kettle", "cup"]);
    assert_eq!(
        subtree(&doc, kids[0].as_u64().unwrap() as usize).len(),
        lib.skeleton.body_names().len()
    );
    let out = run_python(
        &format!("{PY_FK}{PY_GLTF}"),
        &[
            run.to_str().unwrap(),
            &mjcf("mocap_parahome_boxhand"),
            glb.to_str().unwrap(),
            &ids.join(","),
        ],
    );
    assert!(max_error_mm(&out) < 1.0);
    assert!(out.contains("kettle hidden") && out.contains("cup hidden"));
    assert!(out.contains("; kettle 0.") && out.contains("; cup 0."));
    khronos_validator(&glb);
}

/// Validate `glb` with the Khronos glTF validator (npm `gltf-validator`,
/// a Dart build with no dependencies): no errors, no warnings. Needs node;
/// the module is installed under target/ on first use (npm, 400 kB). When
/// node or npm is missing (CI images without them) it says so and returns.
fn khronos_validator(glb: &Path) {
    let have = |cmd: &str| {
        Command::new(cmd)
            .arg("--version")
            .output()
            .map(|o| o.status.success())
            .unwrap_or(false)
    };
    // under CI (`CI` set, `.ci/run` installs node and the validator) a
    // missing validator is a failure, not a skip
    let ci = std::env::var_os("CI").is_some();
    if !have("node") {
        assert!(
            !ci,
            "CI: the Khronos glTF validator needs node (bash .ci/run installs it)"
        );
        eprintln!("Khronos glTF validator skipped: no node on this machine");
        return;
    }
    let prefix = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/gltf-validator");
    let module = prefix.join("node_modules/gltf-validator");
    if !module.join("index.js").exists() {
        let got = have("npm")
            && Command::new("npm")
                .args(["install", "--no-audit", "--no-fund", "--silent", "--prefix"])
                .arg(&prefix)
                .arg("gltf-validator@2.0.0-dev.3.10")
                .status()
                .map(|s| s.success())
                .unwrap_or(false);
        if !got {
            assert!(!ci, "CI: cannot install the npm package gltf-validator");
            eprintln!("Khronos glTF validator skipped: cannot install the npm package");
            return;
        }
    }
    let script = r#"
const v = require(process.argv[1]);
const bytes = new Uint8Array(require("fs").readFileSync(process.argv[2]));
v.validateBytes(bytes, { maxIssues: 20 }).then((r) => {
  const i = r.issues;
  console.log(`validator: ${i.numErrors} errors, ${i.numWarnings} warnings, ${i.numInfos} infos, ${i.numHints} hints`);
  for (const m of i.messages) console.log(`${m.severity} ${m.code} ${m.pointer || ""}: ${m.message}`);
  process.exit(i.numErrors + i.numWarnings > 0 ? 1 : 0);
}, (e) => { console.error(String(e)); process.exit(2); });
"#;
    let o = Command::new("node")
        .arg("-e")
        .arg(script)
        .arg(&module)
        .arg(glb)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    eprint!("{out}");
    assert!(
        o.status.success(),
        "the Khronos validator reports problems:\n{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

#[test]
fn bad_selections_fail_clearly_and_write_nothing() {
    let (dir, run) = ingested("ballplay");
    let bvh = dir.path().join("new_bvh_dir");
    let glb = dir.path().join("out.glb");
    let refused = |extra: &[&str]| -> String {
        let mut a = vec![
            "export",
            "--from",
            run.to_str().unwrap(),
            "--bvh",
            bvh.to_str().unwrap(),
            "--gltf",
            glb.to_str().unwrap(),
        ];
        a.extend_from_slice(extra);
        fails(&a)
    };
    let err = refused(&["--clip", "0", "--clip", "no_such_clip"]);
    assert!(err.contains("no clip `no_such_clip`"), "{err}");
    let err = refused(&["--clip", "99"]);
    assert!(err.contains("no clip `99`"), "{err}");
    let err = refused(&["--clip", "0", "--units", "mm"]);
    assert!(
        err.contains("'mm'") && err.contains("--units") && err.contains("m, cm"),
        "{err}"
    );

    // a rollouts table without recorded steps
    let ev = dir.path().join("ev");
    std::fs::create_dir_all(&ev).unwrap();
    let mut staged = skillaug::table::io::Staged::new();
    staged
        .parquet(
            &ev.join("eval_rollouts.parquet"),
            &skillaug::table::rollout::batch(&[]).unwrap(),
            &skillaug::table::Meta::new("ballplay", "").table("eval_rollouts"),
        )
        .unwrap();
    staged.commit().unwrap();
    let err = refused(&["--rollouts", ev.to_str().unwrap()]);
    assert!(err.contains("no recorded steps"), "{err}");
    let err = refused(&["--rollouts", run.join("clips.parquet").to_str().unwrap()]);
    assert!(err.contains("expected `eval_rollouts`"), "{err}");

    assert!(!bvh.exists(), "the --bvh folder was left behind");
    assert!(!glb.exists());
    assert_eq!(entries(dir.path()), vec!["ev", "run"]);
}

/// A failure after the BVH files are staged (an object mesh missing from
/// the data root, found only when the glTF file is built) leaves neither
/// BVH files nor the folder made for them.
#[test]
fn a_failure_after_the_bvh_files_leaves_no_bvh_folder() {
    let (dir, run) = ingested("parahome");
    let lib = skillaug::table::load_library(&run).unwrap();
    let kettle = lib
        .clips
        .iter()
        .position(|c| c.objects.iter().any(|o| o == "kettle"))
        .unwrap()
        .to_string();
    // a data root with the humanoids but no object meshes
    let data = dir.path().join("data");
    std::fs::create_dir_all(data.join("assets")).unwrap();
    std::os::unix::fs::symlink(data_root().join("assets/mjcf"), data.join("assets/mjcf")).unwrap();
    let bvh = dir.path().join("new_bvh_dir/inner");
    let glb = dir.path().join("out.glb");
    let err = fails(&[
        "export",
        "--from",
        run.to_str().unwrap(),
        "--data-root",
        data.to_str().unwrap(),
        "--clip",
        &kettle,
        "--bvh",
        bvh.to_str().unwrap(),
        "--gltf",
        glb.to_str().unwrap(),
    ]);
    assert!(err.contains("kettle"), "{err}");
    assert!(!glb.exists());
    assert_eq!(
        entries(dir.path()),
        vec!["data", "run"],
        "the --bvh folders were left behind"
    );
}

/// A glTF path that is a folder is found before anything is moved into
/// place: the BVH files staged beside it are not written either.
#[test]
fn a_folder_in_the_way_moves_nothing_into_place() {
    let (dir, run) = ingested("ballplay");
    let bvh = dir.path().join("bvh");
    let glb = dir.path().join("in_the_way.glb");
    std::fs::create_dir_all(&glb).unwrap();
    let err = fails(&[
        "export",
        "--from",
        run.to_str().unwrap(),
        "--clip",
        "0",
        "--bvh",
        bvh.to_str().unwrap(),
        "--gltf",
        glb.to_str().unwrap(),
    ]);
    assert!(err.contains("a folder of that name is in the way"), "{err}");
    assert!(!bvh.exists(), "BVH files were moved into place");
    // with no selection, every clip (as `view` shows them)
    let text = export(&run, &["--bvh", bvh.to_str().unwrap()]);
    assert!(text.contains("exported 6 file(s)"), "{text}");
}

/// Recorded rollouts: a rollout and its reference as two named characters,
/// and only with the clips they were evaluated on.
#[test]
fn rollouts_export_beside_their_reference_and_only_with_their_clips() {
    let (dir, run) = ingested("ballplay");
    let r = run.to_str().unwrap();
    let pol = dir.path().join("pol");
    let mut a = vec!["train", "--from", r, "--out", pol.to_str().unwrap(), "-q"];
    a.extend_from_slice(TINY_TRAIN);
    a.extend_from_slice(&[
        "--set",
        "train.samples=32",
        "--set",
        "train.skills=[\"run\"]",
    ]);
    ok(&a);
    let ev = dir.path().join("ev");
    eval_quiet(
        r,
        &pol,
        &ev,
        &[
            "--record",
            "1",
            "--set",
            "eval.trials=1",
            "--set",
            "eval.envs=1",
            "--set",
            "eval.steps=20",
            "--set",
            "eval.metrics=[\"sr\"]",
        ],
    );
    let glb = dir.path().join("r.glb");
    export(
        &run,
        &[
            "--rollouts",
            ev.to_str().unwrap(),
            "--gltf",
            glb.to_str().unwrap(),
            "-q",
        ],
    );
    let (doc, _) = check_glb(&std::fs::read(&glb).unwrap());
    let names: Vec<&str> = doc["scenes"][0]["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| {
            doc["nodes"][n.as_u64().unwrap() as usize]["name"]
                .as_str()
                .unwrap()
        })
        .collect();
    assert_eq!(names, ["character 0: rollout", "character 1: reference"]);
    khronos_validator(&glb);
    // the same rollouts with another dataset's clips are refused
    let (_other, loco) = ingested("locomotion");
    let out = dir.path().join("wrong");
    let err = fails(&[
        "export",
        "--from",
        loco.to_str().unwrap(),
        "--rollouts",
        ev.to_str().unwrap(),
        "--bvh",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("eval_rollouts.parquet was made from the clips of another ingest run"),
        "{err}"
    );
    assert!(!out.exists());
}
