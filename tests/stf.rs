//! `skillaug sample-stf` and the STF/ATS library on the real BallPlay clips.

mod common;

use arrow::array::{Array, AsArray, Float64Array, UInt32Array};
use arrow::datatypes::{DataType, Field, Schema, UInt32Type};
use arrow::record_batch::RecordBatch;
use common::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use skillaug::augment::ats::{Ats, AtsParams};
use skillaug::augment::stf::{Connect, Noise, Order, StartKind, StfParams, StfSampler};
use skillaug::augment::{n_masked, MaskRule};
use skillaug::motion::MotionLib;
use skillaug::reward::{self, Align, DatasetKind, Weights};
use skillaug::table::{self, io::read_parquet};
use std::path::Path;
use std::sync::Arc;

/// Ingest BallPlay into `dir/run` (and build the STG when asked).
fn run_dir(dir: &Path, stg: bool) -> String {
    let o = dir.join("run").to_str().unwrap().to_string();
    ok(&["ingest", "--dataset", "ballplay", "--out", &o, "-q"]);
    if stg {
        ok(&["build-stg", "--out", &o, "-q"]);
    }
    o
}

fn sk_weights() -> Weights {
    Weights::sm(DatasetKind::BallPlay)
}

/// Brute-force Eq. 6 over every candidate frame of `skill`.
fn best_frame(lib: &MotionLib, skill: &str, start: &skillaug::motion::State) -> (f64, (u32, u32)) {
    let w = sk_weights();
    let mut best = (-1.0, (0, 0));
    for c in lib.clips_of(skill) {
        let n = lib.frames[c].frames;
        for f in 2..n - 1 {
            let s = lib.state(c, f).unwrap();
            let b = reward::similarity(
                &s,
                start,
                lib.skeleton,
                &w,
                Align {
                    xy: false,
                    yaw: false,
                },
            );
            if b > best.0 {
                best = (b, (c as u32, f as u32));
            }
        }
    }
    best
}

#[test]
fn without_switch_and_noise_every_start_is_a_reference_frame() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_dir(dir.path(), false);
    let lib = table::load_library(Path::new(&out)).unwrap();
    let s = StfSampler::new(&lib, &[], sk_weights());
    let ats = Ats::new(&lib).weights(&AtsParams::default());
    let p = StfParams {
        p_e: 0.0,
        p_n: 0.0,
        ..StfParams::default()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for _ in 0..300 {
        let t = s.sample(&ats, &p, &mut rng).unwrap();
        assert_eq!(
            (t.start_kind, t.noised, t.fallback),
            (StartKind::Rsi, false, false)
        );
        assert_eq!(t.beta, 1.0);
        assert_eq!(t.n_masked, 0);
        assert_eq!(t.connect, t.centroid);
        let (c, f) = (t.centroid.0 as usize, t.centroid.1 as usize);
        assert_eq!(t.start, lib.state(c, f).unwrap());
        assert!(f >= 2 && f + 2 <= lib.frames[c].frames);
        assert_eq!(t.condition, lib.clips[c].class as u32);
        assert_eq!(t.steps[1].ref_frame, Some(f as u32));
        assert!(t.steps.iter().all(|st| !st.masked));
    }
}

#[test]
fn sampled_trajectories_keep_their_invariants_over_many_seeds() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_dir(dir.path(), true);
    let lib = table::load_library(Path::new(&out)).unwrap();
    let edges = table::stg::read(&Path::new(&out).join("stg_edges.parquet")).unwrap();
    let s = StfSampler::new(&lib, &edges, sk_weights());
    let ats = Ats::new(&lib).weights(&AtsParams::default());
    let base = StfParams {
        p_e: 0.4,
        p_n: 0.4,
        ..StfParams::default()
    };
    let variants = [
        base.clone(),
        StfParams {
            noise: Noise::Gaussian,
            n_max: 3,
            horizon: 20,
            ..base.clone()
        },
        StfParams {
            order: Order::Reference,
            connect: Connect::Reference,
            mask_rule: MaskRule::Reference,
            ..base.clone()
        },
    ];
    let sk = lib.skeleton;
    let w = sk_weights();
    let mut kinds = std::collections::BTreeSet::new();
    for (v, p) in variants.iter().enumerate() {
        for seed in 0..40u64 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            for k in 0..10 {
                let t = s.sample(&ats, p, &mut rng).unwrap();
                kinds.insert(t.kind_label());
                assert!(
                    t.policy_steps() <= p.horizon && t.policy_steps() >= 1,
                    "{t:?}"
                );
                assert!(t.steps[0].ref_clip.is_none() && !t.steps[0].masked);
                // every reference exists, belongs to A and runs on frame by frame
                let mut prev: Option<u32> = None;
                let mut run = 0;
                for st in &t.steps[1..] {
                    if st.is_inserted() {
                        run += 1;
                        assert!(prev.is_none(), "masked states come before the references");
                        continue;
                    }
                    let (c, f) = (st.ref_clip.unwrap() as usize, st.ref_frame.unwrap());
                    assert_eq!(c, t.connect.0 as usize);
                    assert!((f as usize) < lib.frames[c].frames);
                    assert_eq!(lib.clips[c].skill, t.target_skill);
                    assert_eq!(st.masked, !lib.frames[c].valid[f as usize]);
                    if let Some(pf) = prev {
                        assert_eq!(f, pf + 1);
                    }
                    prev = Some(f);
                }
                assert!(run <= p.n_max, "{run} masked states");
                let want_run = match p.connect {
                    Connect::Paper => t.n_masked,
                    Connect::Reference => t.n_masked.saturating_sub(1),
                };
                assert_eq!(run, want_run.min(p.horizon as u32));
                // the first reference is ŝ_j (or ŝ_{j+1} when the start stands for ŝ_j)
                let first = t.steps.iter().find_map(|st| st.ref_frame);
                let j = t.connect.1 + u32::from(p.connect == Connect::Reference && t.n_masked == 0);
                if let Some(first) = first {
                    assert_eq!(first, j);
                }
                // β is S_k of the start and ŝ_j, and N follows Eq. 20
                let sj = lib
                    .state(t.connect.0 as usize, t.connect.1 as usize)
                    .unwrap();
                let b = if sj == t.start {
                    1.0
                } else {
                    reward::similarity(
                        &sj,
                        &t.start,
                        sk,
                        &w,
                        Align {
                            xy: false,
                            yaw: false,
                        },
                    )
                };
                assert_eq!(b, t.beta);
                if !t.fallback {
                    assert_eq!(
                        Some(t.n_masked),
                        n_masked(t.beta, p.tau, p.n_max, p.mask_rule)
                    );
                    // ŝ_j is the argmax over A (checked on a sample: brute force is slow)
                    if v == 0 && k % 3 == 0 && t.start_kind == StartKind::Stg
                        || t.noised && seed % 7 == 0
                    {
                        let (bb, jj) = best_frame(&lib, &t.target_skill, &t.start);
                        assert_eq!(bb, t.beta, "{t:?}");
                        assert_eq!(jj, t.connect);
                    }
                }
                if p.order == Order::Reference {
                    assert_ne!(t.kind_label(), "stg+noise");
                }
            }
        }
    }
    for k in ["rsi", "rsi+noise", "stg", "stg+noise"] {
        assert!(kinds.contains(k), "{kinds:?}");
    }
    // determinism of the library call for a seed
    let one = |seed| {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..20)
            .map(|_| s.sample(&ats, &base, &mut rng).unwrap())
            .collect::<Vec<_>>()
    };
    assert_eq!(one(5), one(5));
    assert_ne!(one(5), one(6));
}

fn stf_rows(out: &str) -> (usize, Vec<u32>, Vec<u32>, Vec<String>) {
    let t = read_parquet(&Path::new(out).join("stf_samples.parquet")).unwrap();
    assert_eq!(t.meta("skillaug.table"), Some("stf_samples"));
    let (mut id, mut step, mut kind) = (Vec::new(), Vec::new(), Vec::new());
    for b in &t.batches {
        id.extend(
            b.column_by_name("traj_id")
                .unwrap()
                .as_primitive::<UInt32Type>()
                .values()
                .iter(),
        );
        step.extend(
            b.column_by_name("step")
                .unwrap()
                .as_primitive::<UInt32Type>()
                .values()
                .iter(),
        );
        let k = b.column_by_name("start_kind").unwrap().as_string::<i32>();
        kind.extend((0..k.len()).map(|i| k.value(i).to_string()));
        // the start state is filled at step 0 only
        let rp = b.column_by_name("root_pos").unwrap();
        let st = b
            .column_by_name("step")
            .unwrap()
            .as_primitive::<UInt32Type>();
        for i in 0..b.num_rows() {
            assert_eq!(rp.is_null(i), st.value(i) != 0);
        }
    }
    (t.rows(), id, step, kind)
}

#[test]
fn sample_stf_writes_the_table_deterministically() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_dir(dir.path(), true);
    let stdout = ok(&["sample-stf", "--out", &out]);
    assert!(
        stdout.contains("sampled 1000 trajectories") && stdout.contains("mean N"),
        "{stdout}"
    );
    let (rows, id, step, kind) = stf_rows(&out);
    // one row per (trajectory, step): steps run 0, 1, ... within each trajectory
    assert_eq!(step.iter().filter(|s| **s == 0).count(), 1000);
    // rows = the sum of the trajectory lengths: ids 0..999 in order, steps 0, 1, ... within each
    assert_eq!((rows, id.len()), (step.len(), step.len()));
    let (mut expect, mut traj) = (0u32, 0u32);
    for (i, s) in id.iter().zip(&step) {
        if *s == 0 && (*i, expect) != (0, 0) {
            (expect, traj) = (0, traj + 1);
        }
        assert_eq!((*i, *s), (traj, expect));
        assert!(*s <= 60);
        expect += 1;
    }
    assert_eq!(traj, 999);
    for k in ["stg", "rsi+noise"] {
        assert!(kind.iter().any(|x| x == k), "no {k} start");
    }
    assert!(kind.iter().any(|x| x.ends_with("+noise")));
    let resolved =
        std::fs::read_to_string(Path::new(&out).join("sample-stf.resolved.toml")).unwrap();
    assert!(
        resolved.contains("p_e = 0.1") && resolved.contains("trajectories = 1000"),
        "{resolved}"
    );

    // same seed (any thread count) -> same bytes; another seed -> different
    let bytes = || std::fs::read(Path::new(&out).join("stf_samples.parquet")).unwrap();
    let a = bytes();
    ok(&["sample-stf", "--out", &out, "-q", "--threads", "1"]);
    assert!(a == bytes());
    ok(&["sample-stf", "--out", &out, "-q", "--seed", "1"]);
    assert!(a != bytes());
}

#[test]
fn missing_graph_parahome_and_bad_settings_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_dir(dir.path(), false);
    let err = fails(&["sample-stf", "--out", &out]);
    assert!(
        err.contains("stg_edges.parquet") && err.contains("build-stg"),
        "{err}"
    );
    assert!(!Path::new(&out).join("stf_samples.parquet").exists());
    // without the graph p_e = 0 works
    ok(&[
        "sample-stf",
        "--out",
        &out,
        "-q",
        "--set",
        "sample-stf.p_e=0",
        "--set",
        "sample-stf.trajectories=50",
    ]);
    let (_, _, _, kind) = stf_rows(&out);
    assert!(kind.iter().all(|k| k.starts_with("rsi")));
    let err = fails(&["sample-stf", "--out", &out, "--set", "sample-stf.p_n=1.5"]);
    assert!(err.contains("p_n"), "{err}");
    let err = fails(&[
        "sample-stf",
        "--out",
        &out,
        "--set",
        "sample-stf.skills=[\"dunk\"]",
        "--set",
        "sample-stf.p_e=0",
    ]);
    assert!(err.contains("dunk") && err.contains("layup"), "{err}");

    let ph = dir.path().join("ph");
    let ph = ph.to_str().unwrap();
    ok(&["ingest", "--dataset", "parahome", "--out", ph, "-q"]);
    let err = fails(&["sample-stf", "--out", ph]);
    assert!(err.contains("ParaHome") && err.contains("p_e"), "{err}");
    ok(&[
        "sample-stf",
        "--out",
        ph,
        "-q",
        "--set",
        "sample-stf.p_e=0",
        "--set",
        "sample-stf.trajectories=40",
    ]);
}

fn write_rewards(path: &Path, clip: Vec<u32>, frame: Vec<u32>, r: Vec<f64>, reward_name: &str) {
    let schema = Arc::new(Schema::new(vec![
        Field::new("clip_id", DataType::UInt32, false),
        Field::new("frame", DataType::UInt32, false),
        Field::new(reward_name, DataType::Float64, false),
    ]));
    let b = RecordBatch::try_new(
        schema.clone(),
        vec![
            Arc::new(UInt32Array::from(clip)),
            Arc::new(UInt32Array::from(frame)),
            Arc::new(Float64Array::from(r)),
        ],
    )
    .unwrap();
    let f = std::fs::File::create(path).unwrap();
    let mut w = parquet::arrow::ArrowWriter::try_new(f, schema, None).unwrap();
    w.write(&b).unwrap();
    w.close().unwrap();
}

#[test]
fn ats_rewards_steer_the_start_frames() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_dir(dir.path(), false);
    let lib = table::load_library(Path::new(&out)).unwrap();
    // every start frame of every clip did well (0.9) except frame 40 of clip 0 (0.1)
    let (mut c, mut f, mut r) = (Vec::new(), Vec::new(), Vec::new());
    for (ci, cf) in lib.frames.iter().enumerate() {
        for fi in 0..cf.frames {
            c.push(ci as u32);
            f.push(fi as u32);
            r.push(if (ci, fi) == (0, 40) { 0.1 } else { 0.9 });
        }
    }
    let good = dir.path().join("rewards.parquet");
    write_rewards(&good, c.clone(), f.clone(), r.clone(), "mean_reward");
    let set = format!("sample-stf.rewards=\"{}\"", good.display());
    let common = [
        "--set",
        "sample-stf.p_e=0",
        "--set",
        "sample-stf.p_n=0",
        "--set",
        "sample-stf.trajectories=300",
        "--set",
        "sample-stf.lambda_i=5",
    ];
    let mut args = vec!["sample-stf", "--out", &out, "-q", "--set", &set];
    args.extend(common);
    ok(&args);
    let t = read_parquet(&Path::new(&out).join("stf_samples.parquet")).unwrap();
    let (mut at40, mut starts) = (0, 0);
    for b in &t.batches {
        let step = b
            .column_by_name("step")
            .unwrap()
            .as_primitive::<UInt32Type>();
        let cc = b
            .column_by_name("centroid_clip")
            .unwrap()
            .as_primitive::<UInt32Type>();
        let cf = b
            .column_by_name("centroid_frame")
            .unwrap()
            .as_primitive::<UInt32Type>();
        for i in 0..b.num_rows() {
            if step.value(i) == 0 {
                starts += 1;
                at40 += usize::from((cc.value(i), cf.value(i)) == (0, 40));
            }
        }
    }
    // clip 0 (layup) gets 1/5 of the starts; within it exp(8) ≈ 3000 times the weight of any other frame
    assert_eq!(starts, 300);
    assert!(at40 >= 30, "{at40} of {starts} starts at the hard frame");

    // a missing column is an error naming the file and the column
    let bad = dir.path().join("bad.parquet");
    write_rewards(&bad, c, f, r, "reward");
    let set = format!("sample-stf.rewards=\"{}\"", bad.display());
    let mut args = vec!["sample-stf", "--out", &out, "--set", &set];
    args.extend(common);
    let err = fails(&args);
    assert!(
        err.contains("bad.parquet") && err.contains("mean_reward"),
        "{err}"
    );
    let set = format!(
        "sample-stf.rewards=\"{}\"",
        dir.path().join("none.parquet").display()
    );
    let mut args = vec!["sample-stf", "--out", &out, "--set", &set];
    args.extend(common);
    let err = fails(&args);
    assert!(err.contains("none.parquet"), "{err}");
}
