//! Bad input: every case exits with code 1, names the file and the problem,
//! and leaves nothing behind (and nothing already there is lost).

mod common;

use common::*;
use std::path::{Path, PathBuf};

const GOOD: &str = "ballplay/run/013_018pickle_run_4.pt";

/// A `--from` folder with one good clip and one bad one (`bytes`), an output
/// folder already holding an earlier run's file; ingest must fail, name the
/// bad file and the problem, and leave the output folder untouched.
fn rejects(bad_name: &str, bytes: &[u8], problem: &str) {
    let dir = tempfile::tempdir().unwrap();
    let clips = dir.path().join("clips/run");
    std::fs::create_dir_all(&clips).unwrap();
    std::fs::copy(data_root().join(GOOD), clips.join("013_good.pt")).unwrap();
    std::fs::write(clips.join(bad_name), bytes).unwrap();
    rejects_folder(dir.path(), bad_name, problem);
}

fn rejects_folder(dir: &Path, bad_name: &str, problem: &str) {
    let out = dir.join("run");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("frames.parquet"), b"earlier output").unwrap();
    let from = dir.join("clips");
    let err = fails(&[
        "ingest",
        "--from",
        from.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains(bad_name),
        "message does not name {bad_name}:\n{err}"
    );
    assert!(
        err.to_lowercase().contains(&problem.to_lowercase()),
        "message does not say `{problem}`:\n{err}"
    );
    assert_eq!(entries(&out), ["frames.parquet"], "output folder changed");
    assert_eq!(
        std::fs::read(out.join("frames.parquet")).unwrap(),
        b"earlier output"
    );

    // A fresh output folder is not even created.
    let fresh = dir.join("fresh");
    fails(&[
        "ingest",
        "--from",
        from.to_str().unwrap(),
        "--out",
        fresh.to_str().unwrap(),
    ]);
    assert!(!fresh.exists(), "a failed run left {}", fresh.display());

    // --skip-bad ingests the good clip and lists the bad one.
    let o = skillaug(&[
        "ingest",
        "--from",
        from.to_str().unwrap(),
        "--out",
        fresh.to_str().unwrap(),
        "--skip-bad",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "--skip-bad failed: {err}");
    assert!(
        err.contains("skipped 1 bad clip") && err.contains(bad_name),
        "{err}"
    );
    assert!(String::from_utf8_lossy(&o.stdout).contains("ingested 1 clips"));
}

fn real_bytes() -> Vec<u8> {
    std::fs::read(data_root().join(GOOD)).unwrap()
}

#[test]
fn truncated_zip() {
    rejects("013_trunc.pt", &real_bytes()[..100], "zip");
}

#[test]
fn corrupt_zip() {
    let mut b = real_bytes();
    let n = b.len();
    // Overwrite the end-of-central-directory record.
    b[n - 22..].iter_mut().for_each(|x| *x = 0xAB);
    rejects("013_corrupt.pt", &b, "zip");
    rejects("013_garbage.pt", b"this is not a zip archive at all", "zip");
}

#[test]
fn pickle_holding_a_dict() {
    // {'a': 1} at protocol 2
    let pickle = b"\x80\x02}q\x00X\x01\x00\x00\x00aq\x01K\x01s.";
    rejects("013_dict.pt", &pt_archive(pickle, &[]), "dict");
}

#[test]
fn int_tensor() {
    let data: Vec<u8> = (0..337i64 * 2).flat_map(|v| v.to_le_bytes()).collect();
    let pickle = tensor_pickle("LongStorage", 337 * 2, &[2, 337], &[337, 1]);
    rejects("013_long.pt", &pt_archive(&pickle, &data), "float32");
}

#[test]
fn wrong_column_count() {
    rejects(
        "013_wide.pt",
        &f32_pt(3, 336, &vec![0.5; 3 * 336]),
        "336 columns",
    );
}

#[test]
fn nan_and_inf_values() {
    let (f, d, mut x) = read_clip(&data_root().join(GOOD));
    x[5 * d + 100] = f32::NAN;
    rejects(
        "013_nan.pt",
        &f32_pt(f, d, &x),
        "non-finite value NaN at frame 5, column 100",
    );
    x[5 * d + 100] = 0.0;
    x[7 * d + 2] = f32::INFINITY;
    rejects(
        "013_inf.pt",
        &f32_pt(f, d, &x),
        "non-finite value inf at frame 7, column 2",
    );
}

#[test]
fn unreadable_file() {
    let dir = tempfile::tempdir().unwrap();
    let clips = dir.path().join("clips/run");
    std::fs::create_dir_all(&clips).unwrap();
    std::fs::copy(data_root().join(GOOD), clips.join("013_good.pt")).unwrap();
    // A dangling link: listed as a clip, cannot be read (even by root).
    std::os::unix::fs::symlink(dir.path().join("nowhere"), clips.join("013_gone.pt")).unwrap();
    rejects_folder(dir.path(), "013_gone.pt", "cannot read");
}

#[test]
fn unknown_dataset_and_manifest_keys() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o");
    let err = fails(&[
        "ingest",
        "--dataset",
        "nope",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("unknown dataset `nope`") && err.contains("ballplay"),
        "{err}"
    );
    assert!(!out.exists());

    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("datasets/ballplay.toml"),
    )
    .unwrap()
    .replace("fps = 60", "fps = 60\nframe_rate = 60");
    let m = dir.path().join("odd.toml");
    std::fs::write(&m, text).unwrap();
    let err = fails(&[
        "ingest",
        "--dataset",
        m.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("odd.toml") && err.contains("frame_rate"),
        "{err}"
    );

    let err = fails(&[
        "ingest",
        "--dataset",
        "ballplay-m",
        "--set",
        "ingest.split=pickup-5",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("unknown split `pickup-5`") && err.contains("pickup-4"),
        "{err}"
    );
    assert!(!out.exists());
}

#[test]
fn changed_clip_is_refused_by_hash() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("data");
    let dst: PathBuf = root.join(GOOD);
    std::fs::create_dir_all(dst.parent().unwrap()).unwrap();
    std::fs::copy(data_root().join(GOOD), &dst).unwrap();
    // Change one value of the clip.
    let (f, d, mut x) = read_clip(&root.join(GOOD));
    x[0] += 1.0;
    std::fs::write(root.join(GOOD), f32_pt(f, d, &x)).unwrap();
    let manifest = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("datasets/ballplay.toml"),
    )
    .unwrap();
    // Keep only the run_4 clip.
    let mut kept = String::new();
    for block in manifest.split("\n[[clip]]\n") {
        if !block.contains("file = ") || block.contains("run/013_018pickle_run_4.pt") {
            if block.contains("file = ") {
                kept.push_str("\n[[clip]]\n");
            }
            kept.push_str(block);
        }
    }
    let m = dir.path().join("one.toml");
    std::fs::write(&m, kept).unwrap();
    let out = dir.path().join("out");
    let err = fails(&[
        "ingest",
        "--dataset",
        m.to_str().unwrap(),
        "--data-root",
        root.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        err.contains("013_018pickle_run_4.pt") && err.contains("sha256"),
        "{err}"
    );
    assert!(!out.exists());
}

#[test]
fn missing_data_root_says_where_to_put_the_releases() {
    let err = fails(&[
        "ingest",
        "--dataset",
        "ballplay",
        "--data-root",
        "/nonexistent/skillaug",
        "--out",
        "/tmp/never",
    ]);
    assert!(
        err.contains("/nonexistent/skillaug") && err.contains("BallPlay-M"),
        "{err}"
    );
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_skillaug"))
        .args(["ingest", "--dataset", "ballplay", "--out", "/tmp/never"])
        .env("SKILLAUG_DATA", "/nonexistent/env-root")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent/env-root"));
}

#[test]
fn unknown_recipe_and_set_keys_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = dir.path().join("r.toml");
    std::fs::write(&recipe, "[ingest]\nsplitt = \"pickup-4\"\n").unwrap();
    let out = dir.path().join("o");
    let err = fails(&[
        "ingest",
        "--dataset",
        "ballplay",
        "--recipe",
        recipe.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(err.contains("splitt") && err.contains("r.toml"), "{err}");
    let err = fails(&[
        "ingest",
        "--dataset",
        "ballplay",
        "--set",
        "ingest.fsp=30",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(err.contains("fsp") && err.contains("--set"), "{err}");
    std::fs::write(&recipe, "[injest]\nfps = 30\n").unwrap();
    let err = fails(&[
        "ingest",
        "--dataset",
        "ballplay",
        "--recipe",
        recipe.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(err.contains("[injest]") && err.contains("r.toml"), "{err}");
    assert!(!out.exists());
}
