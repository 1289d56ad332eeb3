//! `skillaug build-stg` on the real BallPlay clips.

mod common;

use common::*;
use skillaug::augment::{n_masked, stg::Edge, MaskRule};
use skillaug::reward::{self, Align, DatasetKind, Weights};
use skillaug::table::{self, io::read_parquet};
use std::path::Path;

#[test]
fn paper_direction_edges_are_argmax_connections_with_eq20_counts() {
    let (_dir, out) = ingested("ballplay");
    let out = out.to_str().unwrap().to_string();
    let stdout = ok(&["build-stg", "--out", &out]);
    assert!(stdout.contains("built "), "{stdout}");
    let lib = table::load_library(Path::new(&out)).unwrap();
    let edges = table::stg::read(&Path::new(&out).join("stg_edges.parquet")).unwrap();
    let w = Weights::sm(DatasetKind::BallPlay);
    let sk = lib.skeleton;
    // Every valid frame of every other skill is considered once per target skill.
    let summary = read_parquet(&Path::new(&out).join("stg_summary.parquet")).unwrap();
    assert_eq!(summary.rows(), 5);
    let total: usize = lib.frames.iter().map(|c| c.frames).sum();
    for skill in lib.skills() {
        let own: usize = lib
            .clips_of(&skill)
            .iter()
            .map(|c| lib.frames[*c].frames)
            .sum();
        let kept = edges.iter().filter(|e| e.target_skill == skill).count();
        assert!(kept <= total - own && kept > 0, "{skill}: {kept}");
    }
    for (k, e) in edges.iter().enumerate() {
        assert_ne!(e.src_skill, e.target_skill);
        assert_eq!(lib.clips[e.dst_clip as usize].skill, e.target_skill);
        let f = lib.frames[e.dst_clip as usize].frames as u32;
        assert!(e.dst_frame >= 2 && e.dst_frame < f - 1, "{e:?}");
        assert!(e.beta > 1e-10 && e.beta <= 1.0);
        assert_eq!(
            Some(e.n_masked),
            n_masked(e.beta, 1e-10, 10, MaskRule::Paper)
        );
        // beta is S_k of the aligned start and the target frame...
        let start = e.aligned_start(&lib).unwrap();
        let target = lib
            .state(e.dst_clip as usize, e.dst_frame as usize)
            .unwrap();
        let direct = reward::similarity(
            &target,
            &start,
            sk,
            &w,
            Align {
                xy: false,
                yaw: false,
            },
        );
        assert!(
            (direct - e.beta).abs() <= 1e-4 * e.beta.max(1e-6),
            "{k}: {direct} vs {}",
            e.beta
        );
        // ...and the best over every candidate frame of the target skill (checked on a sample).
        if k % 97 == 0 {
            let src = lib
                .state(e.src_clip as usize, e.src_frame as usize)
                .unwrap();
            let mut best = 0.0f64;
            for c in lib.clips_of(&e.target_skill) {
                for fr in 2..lib.frames[c].frames - 1 {
                    let t = lib.state(c, fr).unwrap();
                    best = best.max(reward::similarity(&t, &src, sk, &w, Align::default()));
                }
            }
            assert!(
                (best - e.beta).abs() <= 1e-6 * best.max(1e-9),
                "{k}: best {best} vs {}",
                e.beta
            );
        }
    }
}

#[test]
fn per_target_mode_gives_each_frame_one_edge_per_other_skill() {
    let (_dir, out) = ingested("ballplay");
    let out = out.to_str().unwrap().to_string();
    ok(&[
        "build-stg",
        "--out",
        &out,
        "--per-target",
        "--set",
        "build-stg.mask_rule=reference",
        "-q",
    ]);
    let lib = table::load_library(Path::new(&out)).unwrap();
    let edges: Vec<Edge> = table::stg::read(&Path::new(&out).join("stg_edges.parquet")).unwrap();
    // 796 frames x 4 other skills, less any dropped (none at tau = 1e-10 here)
    let total: usize = lib.frames.iter().map(|c| c.frames).sum();
    assert_eq!(edges.len(), total * 4);
    for e in &edges {
        assert_eq!(
            Some(e.n_masked),
            n_masked(e.beta, 1e-10, 10, MaskRule::Reference)
        );
        let f = lib.frames[e.src_clip as usize].frames as u32;
        assert!(e.src_frame >= 2 && e.src_frame < f - 1);
    }
    let text = std::fs::read_to_string(Path::new(&out).join("build-stg.resolved.toml")).unwrap();
    assert!(
        text.contains("per_target = true") && text.contains("mask_rule = \"reference\""),
        "{text}"
    );
}

#[test]
fn outputs_are_deterministic_and_parahome_is_refused() {
    let (dir, out) = ingested("ballplay");
    let out = out.to_str().unwrap().to_string();
    ok(&["build-stg", "--out", &out, "-q", "--threads", "2"]);
    let a = std::fs::read(Path::new(&out).join("stg_edges.parquet")).unwrap();
    ok(&["build-stg", "--out", &out, "-q", "--threads", "2"]);
    let b = std::fs::read(Path::new(&out).join("stg_edges.parquet")).unwrap();
    assert!(a == b);

    let ph = dir.path().join("ph");
    ok(&[
        "ingest",
        "--dataset",
        "parahome",
        "--out",
        ph.to_str().unwrap(),
        "-q",
    ]);
    let err = fails(&["build-stg", "--out", ph.to_str().unwrap()]);
    assert!(err.contains("ParaHome"), "{err}");
    assert_eq!(
        entries(&ph),
        ["clips.parquet", "frames.parquet", "ingest.resolved.toml"]
    );

    let empty = dir.path().join("empty");
    let err = fails(&["build-stg", "--out", empty.to_str().unwrap()]);
    assert!(
        err.contains("clips.parquet") && err.contains("skillaug ingest"),
        "{err}"
    );
}

#[test]
fn dataset_kind_follows_the_clips_not_the_folder_name() {
    let dir = tempfile::tempdir().unwrap();
    for (name, kind) in [
        ("locomotion", DatasetKind::Locomotion),
        ("ballplay", DatasetKind::BallPlay),
        ("parahome", DatasetKind::ParaHome),
    ] {
        let out = dir.path().join(name);
        ok(&[
            "ingest",
            "--dataset",
            name,
            "--out",
            out.to_str().unwrap(),
            "-q",
        ]);
        assert_eq!(
            DatasetKind::of_library(&table::load_library(&out).unwrap()),
            kind
        );
    }
}
