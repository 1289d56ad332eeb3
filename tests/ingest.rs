//! `skillaug ingest` on the real clips: values straight from the tensor are
//! stored bit for bit, derived velocities follow the reference loader
//! (Ingrid789/SkillMimic-V2 `skillmimic/utils/motion_data_handler.py`), outputs
//! are deterministic, and an independent reader (pyarrow) reads them.

mod common;

use arrow::array::{
    Array, AsArray, BooleanArray, FixedSizeListArray, ListArray, StringArray, UInt32Array,
};
use arrow::datatypes::Float32Type;
use common::*;
use skillaug::table::io::{read_parquet, ReadTable};
use std::path::Path;

/// Rows of a float list column (fixed or variable size) as optional vectors.
fn f32_rows(t: &ReadTable, name: &str) -> Vec<Option<Vec<f32>>> {
    let mut out = Vec::new();
    for b in &t.batches {
        let col = b
            .column_by_name(name)
            .unwrap_or_else(|| panic!("no column {name}"));
        for i in 0..col.len() {
            if col.is_null(i) {
                out.push(None);
                continue;
            }
            let v = if let Some(l) = col.as_any().downcast_ref::<FixedSizeListArray>() {
                l.value(i)
            } else {
                col.as_any().downcast_ref::<ListArray>().unwrap().value(i)
            };
            out.push(Some(v.as_primitive::<Float32Type>().values().to_vec()));
        }
    }
    out
}

fn u32s(t: &ReadTable, name: &str) -> Vec<u32> {
    t.batches
        .iter()
        .flat_map(|b| {
            b.column_by_name(name)
                .unwrap()
                .as_any()
                .downcast_ref::<UInt32Array>()
                .unwrap()
                .values()
                .to_vec()
        })
        .collect()
}

fn strs(t: &ReadTable, name: &str) -> Vec<String> {
    t.batches
        .iter()
        .flat_map(|b| {
            let a = b.column_by_name(name).unwrap();
            let a = a.as_any().downcast_ref::<StringArray>().unwrap();
            (0..a.len())
                .map(|i| a.value(i).to_string())
                .collect::<Vec<_>>()
        })
        .collect()
}

fn bools(t: &ReadTable, name: &str) -> Vec<Option<bool>> {
    t.batches
        .iter()
        .flat_map(|b| {
            let a = b.column_by_name(name).unwrap();
            let a = a.as_any().downcast_ref::<BooleanArray>().unwrap();
            (0..a.len())
                .map(|i| (!a.is_null(i)).then(|| a.value(i)))
                .collect::<Vec<_>>()
        })
        .collect()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn quat_from_expmap(e: [f64; 3]) -> [f64; 4] {
    let a = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt();
    if a <= 1e-5 {
        return [0.0, 0.0, 0.0, 1.0];
    }
    let s = (a / 2.0).sin() / a;
    [e[0] * s, e[1] * s, e[2] * s, (a / 2.0).cos()]
}

/// Check every clip of an ingested folder against its source tensor.
fn check_against_tensors(out: &Path, expect_clips: usize) {
    let clips = read_parquet(&out.join("clips.parquet")).unwrap();
    let frames = read_parquet(&out.join("frames.parquet")).unwrap();
    assert_eq!(clips.rows(), expect_clips);
    assert_eq!(frames.meta("skillaug.table"), Some("frames"));
    assert_eq!(frames.meta("skillaug.quaternion_order"), Some("xyzw"));
    let sources = strs(&clips, "source");
    let n_frames = u32s(&clips, "frames");
    let fps: Vec<f32> = clips.batches[0]
        .column_by_name("fps")
        .unwrap()
        .as_primitive::<Float32Type>()
        .values()
        .to_vec();
    let n_obj: Vec<usize> = {
        let l = clips.batches[0].column_by_name("objects").unwrap();
        let l = l.as_any().downcast_ref::<ListArray>().unwrap();
        (0..l.len()).map(|i| l.value(i).len()).collect()
    };
    assert_eq!(frames.rows(), n_frames.iter().sum::<u32>() as usize);
    let clip_id = u32s(&frames, "clip_id");
    let root_pos = f32_rows(&frames, "root_pos");
    let root_exp = f32_rows(&frames, "root_rot_expmap");
    let root_rot = f32_rows(&frames, "root_rot");
    let root_lin = f32_rows(&frames, "root_linvel");
    let root_ang = f32_rows(&frames, "root_angvel");
    let joint = f32_rows(&frames, "joint_rot");
    let joint_vel = f32_rows(&frames, "joint_vel");
    let body = f32_rows(&frames, "body_pos");
    let obj_pos = f32_rows(&frames, "obj_pos");
    let obj_exp = f32_rows(&frames, "obj_rot_expmap");
    let contact = bools(&frames, "contact");

    let mut row = 0;
    for (c, src) in sources.iter().enumerate() {
        let path = if Path::new(src).is_absolute() {
            src.into()
        } else {
            data_root().join(src)
        };
        let (f, d, x) = read_clip(&path);
        assert_eq!(f as u32, n_frames[c], "{src}");
        let (nj, body_start, nb) = if d == 337 {
            (52, 165, 53)
        } else {
            (60, 189, 61)
        };
        let objs: &[(usize, usize)] = match d {
            337 => &[(324, 327)],
            409 => &[(402, 405)],
            _ => &[(402, 405), (408, 411)],
        };
        let objs = &objs[..n_obj[c]];
        let dt = fps[c] as f64;
        for i in 0..f {
            let r = &x[i * d..(i + 1) * d];
            let k = row + i;
            assert_eq!(clip_id[k] as usize, c);
            assert_eq!(
                bits(root_pos[k].as_ref().unwrap()),
                bits(&r[0..3]),
                "{src} frame {i}"
            );
            assert_eq!(bits(root_exp[k].as_ref().unwrap()), bits(&r[3..6]));
            assert_eq!(bits(joint[k].as_ref().unwrap()), bits(&r[9..9 + 3 * nj]));
            assert_eq!(
                bits(body[k].as_ref().unwrap()),
                bits(&r[body_start..body_start + 3 * nb])
            );
            let op: Vec<f32> = objs.iter().flat_map(|o| r[o.0..o.0 + 3].to_vec()).collect();
            assert_eq!(bits(obj_pos[k].as_ref().unwrap()), bits(&op));
            let sign = if d == 337 { -1.0f32 } else { 1.0 };
            let oe: Vec<f32> = objs
                .iter()
                .flat_map(|o| {
                    r[o.1..o.1 + 3]
                        .iter()
                        .map(|v| sign * v + 0.0)
                        .collect::<Vec<_>>()
                })
                .collect();
            assert_eq!(bits(obj_exp[k].as_ref().unwrap()), bits(&oe));
            assert_eq!(contact[k], Some(r[d - 1] == 1.0));
            assert!(r[d - 1] == 0.0 || r[d - 1] == 1.0);

            // Derived: backward differences times fps, zero at frame 0.
            let q = root_rot[k].as_ref().unwrap();
            let want_q = quat_from_expmap([r[3] as f64, r[4] as f64, r[5] as f64]);
            let dotq: f64 = (0..4).map(|j| q[j] as f64 * want_q[j]).sum();
            assert!(
                (dotq.abs() - 1.0).abs() < 1e-5,
                "{src} {i}: {q:?} vs {want_q:?}"
            );
            if i == 0 {
                assert_eq!(root_lin[k].as_ref().unwrap(), &[0.0; 3]);
                assert_eq!(root_ang[k].as_ref().unwrap(), &[0.0; 3]);
                continue;
            }
            let p = &x[(i - 1) * d..i * d];
            let prev_q = root_rot[k - 1].as_ref().unwrap();
            let dot_prev: f32 = (0..4).map(|j| q[j] * prev_q[j]).sum();
            assert!(dot_prev >= 0.0, "{src} {i}: quaternion sign not smoothed");
            for j in 0..3 {
                let want = (r[j] as f64 - p[j] as f64) * dt;
                let got = root_lin[k].as_ref().unwrap()[j] as f64;
                assert!(
                    (got - want).abs() <= 1e-5 * want.abs().max(1.0),
                    "{src} {i}"
                );
            }
            for j in 0..3 * nj {
                let want = (r[9 + j] as f64 - p[9 + j] as f64) * dt;
                let got = joint_vel[k].as_ref().unwrap()[j] as f64;
                assert!((got - want).abs() <= 1e-5 * want.abs().max(1.0));
            }
            // Body-frame angular velocity: rotating the previous quaternion by
            // w/fps (in its own frame) gives the current one.
            let w = root_ang[k].as_ref().unwrap();
            let step = quat_from_expmap([w[0] as f64 / dt, w[1] as f64 / dt, w[2] as f64 / dt]);
            let pq = [
                prev_q[0] as f64,
                prev_q[1] as f64,
                prev_q[2] as f64,
                prev_q[3] as f64,
            ];
            let composed = [
                pq[3] * step[0] + pq[0] * step[3] + pq[1] * step[2] - pq[2] * step[1],
                pq[3] * step[1] - pq[0] * step[2] + pq[1] * step[3] + pq[2] * step[0],
                pq[3] * step[2] + pq[0] * step[1] - pq[1] * step[0] + pq[2] * step[3],
                pq[3] * step[3] - pq[0] * step[0] - pq[1] * step[1] - pq[2] * step[2],
            ];
            let agree: f64 = (0..4).map(|j| composed[j] * q[j] as f64).sum();
            assert!(
                agree.abs() > 1.0 - 1e-6,
                "{src} {i}: angular velocity {w:?}"
            );
        }
        row += f;
    }
}

#[test]
fn every_dataset_ingests_bit_exact_with_reference_velocities() {
    for (name, clips) in [
        ("ballplay", 6),
        ("ballplay-m", 58),
        ("locomotion", 12),
        ("parahome", 7),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("run");
        let stdout = ok(&["ingest", "--dataset", name, "--out", out.to_str().unwrap()]);
        assert!(
            stdout.contains(&format!("ingested {clips} clips")),
            "{stdout}"
        );
        check_against_tensors(&out, clips);
        assert_eq!(
            entries(&out),
            ["clips.parquet", "frames.parquet", "ingest.resolved.toml"]
        );
    }
}

#[test]
fn clips_table_records_manifest_facts() {
    let (_dir, out) = ingested("parahome");
    let clips = read_parquet(&out.join("clips.parquet")).unwrap();
    let labels = strs(&clips, "label");
    assert!(labels.contains(&"Stand-Chair".to_string()));
    let layouts = strs(&clips, "layout");
    let kettlecup = strs(&clips, "skill")
        .iter()
        .position(|s| s == "pour_kettlecup")
        .unwrap();
    assert_eq!(layouts[kettlecup], "D415");
    let class = clips.batches[0]
        .column_by_name("class")
        .unwrap()
        .as_any()
        .downcast_ref::<UInt32Array>()
        .unwrap()
        .value(kettlecup);
    assert_eq!(class, 10);
    assert_eq!(clips.meta("skillaug.fps"), Some("30"));
    assert_eq!(clips.meta("skillaug.n_bodies"), Some("61"));
    let hashes: serde_json::Value =
        serde_json::from_str(clips.meta("skillaug.source_sha256").unwrap()).unwrap();
    assert_eq!(hashes.as_object().unwrap().len(), 7);
}

#[test]
fn locomotion_drops_the_dummy_ball_and_splits_select_clips() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("loco");
    ok(&[
        "ingest",
        "--dataset",
        "locomotion",
        "--out",
        out.to_str().unwrap(),
        "-q",
    ]);
    let frames = read_parquet(&out.join("frames.parquet")).unwrap();
    assert!(f32_rows(&frames, "obj_pos")
        .iter()
        .all(|r| r.as_ref().unwrap().is_empty()));

    let out = dir.path().join("pick");
    ok(&[
        "ingest",
        "--dataset",
        "ballplay-m",
        "--set",
        "ingest.split=pickup-4",
        "--out",
        out.to_str().unwrap(),
        "-q",
    ]);
    let clips = read_parquet(&out.join("clips.parquet")).unwrap();
    assert_eq!(
        strs(&clips, "name"),
        [
            "001_007pickle_pick_000",
            "001_007pickle_pick_001",
            "001_007pickle_pick_002",
            "001_007pickle_pick_003"
        ]
    );
    assert_eq!(u32s(&clips, "clip_id"), [0, 1, 2, 3]);
}

#[test]
fn outputs_are_byte_identical_across_runs_and_thread_counts() {
    let dir = tempfile::tempdir().unwrap();
    let mut files = Vec::new();
    for (k, threads) in ["2", "2", "1"].iter().enumerate() {
        let out = dir.path().join(format!("r{k}"));
        ok(&[
            "ingest",
            "--dataset",
            "ballplay",
            "--seed",
            "7",
            "--threads",
            threads,
            "--out",
            out.to_str().unwrap(),
            "-q",
        ]);
        files.push((
            std::fs::read(out.join("frames.parquet")).unwrap(),
            std::fs::read(out.join("clips.parquet")).unwrap(),
        ));
    }
    assert!(
        files[0] == files[1],
        "same seed and threads, different bytes"
    );
    assert!(files[0] == files[2], "thread count changed the bytes");
}

#[test]
fn missing_frames_become_invalid_rows_with_carried_velocities() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("clips/run");
    std::fs::create_dir_all(&src).unwrap();
    let (f, d, mut x) = read_clip(&data_root().join("ballplay/run/013_018pickle_run_4.pt"));
    for i in [10usize, 11, 40] {
        x[i * d..(i + 1) * d].iter_mut().for_each(|v| *v = 0.0);
    }
    std::fs::write(src.join("013_test_missing.pt"), f32_pt(f, d, &x)).unwrap();
    let out = dir.path().join("run");
    ok(&[
        "ingest",
        "--from",
        dir.path().join("clips").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "-q",
    ]);

    let clips = read_parquet(&out.join("clips.parquet")).unwrap();
    assert_eq!(u32s(&clips, "valid_frames"), [f as u32 - 3]);
    assert_eq!(strs(&clips, "skill"), ["run"]);
    let frames = read_parquet(&out.join("frames.parquet")).unwrap();
    let valid = bools(&frames, "valid");
    let lin = f32_rows(&frames, "root_linvel");
    let body_vel = f32_rows(&frames, "body_vel");
    let contact = bools(&frames, "contact");
    for i in 0..f {
        let missing = [10, 11, 40].contains(&i);
        assert_eq!(valid[i], Some(!missing));
        assert_eq!(lin[i].is_none(), missing, "frame {i}");
        assert_eq!(contact[i].is_none(), missing);
    }
    // The frame after a missing one carries the last good velocity forward.
    assert_eq!(lin[12], lin[9]);
    assert_eq!(body_vel[12], body_vel[9]);
    assert_eq!(lin[41], lin[39]);
    assert_ne!(lin[13], lin[9]);
    let want: Vec<f32> = (0..3)
        .map(|j| ((x[13 * d + j] as f64 - x[12 * d + j] as f64) * 60.0) as f32)
        .collect();
    assert_eq!(lin[13].as_ref().unwrap(), &want);
}

#[test]
fn pyarrow_reads_the_tables() {
    let (_dir, out) = ingested("ballplay");
    let script = r##"
import sys, pyarrow.parquet as pq
out = sys.argv[1]
clips = pq.read_table(out + "/clips.parquet")
frames = pq.read_table(out + "/frames.parquet")
assert clips.num_rows == 6, clips.num_rows
assert frames.num_rows == sum(clips.column("frames").to_pylist()), frames.num_rows
names = [f.name for f in frames.schema]
want = open(sys.argv[2]).read().splitlines()
want = [l.split(":")[0].strip() for l in want if l and not l.startswith("#")]
assert names == want, (names, want)
assert str(frames.schema.field("root_rot").type) == "fixed_size_list<item: float not null>[4]", frames.schema.field("root_rot").type
assert str(frames.schema.field("joint_rot").type) == "list<item: float not null>"
meta = pq.read_metadata(out + "/frames.parquet").metadata
assert meta[b"skillaug.table"] == b"frames" and meta[b"skillaug.quaternion_order"] == b"xyzw"
row = frames.slice(0, 1).to_pylist()[0]
assert len(row["joint_rot"]) == 156 and len(row["body_pos"]) == 159
print("pyarrow", clips.num_rows, frames.num_rows)
"##;
    let python = python_with(&["pyarrow"]);
    let o = std::process::Command::new(&python)
        .arg("-c")
        .arg(script)
        .arg(&out)
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas/frames.txt"))
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "pyarrow check failed:\n{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(String::from_utf8_lossy(&o.stdout).contains("pyarrow 6 "));
}

#[test]
fn the_library_reads_back_what_ingest_derived() {
    let (_dir, out) = ingested("parahome");
    let lib = skillaug::table::load_library(&out).unwrap();
    assert_eq!(lib.clips.len(), 7);
    assert_eq!(lib.skills().len(), 7);
    let kc = lib.clips_of("pour_kettlecup")[0];
    let (f, d, x) = read_clip(&data_root().join(&lib.clips[kc].source));
    assert_eq!(d, 415);
    let s = lib.state(kc, f - 1).unwrap();
    assert_eq!(s.root_pos, x[(f - 1) * d..(f - 1) * d + 3]);
    assert_eq!(s.obj_pos.len(), 6);
    assert_eq!(s.obj_pos[3..], x[(f - 1) * d + 408..(f - 1) * d + 411]);
    assert_eq!(s.joint_rot.len(), 180);
    assert!(lib.state(kc, f).is_none());
}
