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

// ---- bad input refused with a message, nothing written: empty clips,
// ---- nonsense settings, class ids, two writers, file modes

const LRUN: &str = "ballplay/lrun/011_018pickle_lrun_2.pt";

/// The real run clip `GOOD` with the rows for which `zero(row, rows)` holds
/// set to zero (the releases' missing-frame marker).
fn run_clip_zeroed(zero: impl Fn(usize, usize) -> bool) -> Vec<u8> {
    let (f, d, mut x) = read_clip(&data_root().join(GOOD));
    for r in 0..f {
        if zero(r, f) {
            x[r * d..(r + 1) * d].iter_mut().for_each(|v| *v = 0.0);
        }
    }
    f32_pt(f, d, &x)
}

/// A `--from` folder under `dir` with the real lrun clip and the given
/// extra clips (path under the folder, bytes).
fn clip_folder(dir: &Path, extra: &[(&str, Vec<u8>)]) -> PathBuf {
    let from = dir.join("clips");
    std::fs::create_dir_all(from.join("lrun")).unwrap();
    std::fs::copy(
        data_root().join(LRUN),
        from.join("lrun/011_018pickle_lrun_2.pt"),
    )
    .unwrap();
    for (name, bytes) in extra {
        let p = from.join(name);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, bytes).unwrap();
    }
    from
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn clips_without_two_consecutive_valid_frames_are_reported_by_ingest() {
    let dir = tempfile::tempdir().unwrap();
    for (name, bytes, problem) in [
        (
            "013_empty.pt",
            run_clip_zeroed(|_, _| true),
            "no valid frame (all 81 rows are zero",
        ),
        (
            "013_single.pt",
            run_clip_zeroed(|r, _| r != 5),
            "1 valid frame(s) of 81 and no two consecutive ones",
        ),
        (
            "013_apart.pt",
            run_clip_zeroed(|r, _| r % 2 == 1),
            "no two consecutive ones",
        ),
    ] {
        let case = dir.path().join(name);
        let from = clip_folder(&case, &[(&format!("run/{name}"), bytes)]);
        let out = case.join("out");
        let err = fails(&["ingest", "--from", s(&from), "--out", s(&out)]);
        assert!(err.contains(name) && err.contains(problem), "{err}");
        assert!(!out.exists(), "a failed ingest left {}", out.display());
        // --skip-bad leaves it out and says the skill has no clip left
        let o = skillaug(&[
            "ingest",
            "--from",
            s(&from),
            "--out",
            s(&out),
            "-q",
            "--skip-bad",
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{err}");
        assert!(
            err.contains(name) && err.contains("skill(s) left with no clip") && err.contains("run"),
            "{err}"
        );
        // and a stage asked for the vanished skill names it before any work
        let err = fails(&[
            "train",
            "--from",
            s(&out),
            "--out",
            s(&case.join("train")),
            "--set",
            "train.skills=[\"run\"]",
        ]);
        assert!(err.contains("no skill `run`"), "{err}");
        assert!(!case.join("train").exists());
    }
}

#[test]
fn zero_rows_at_the_start_in_a_gap_and_at_the_end_go_through_every_stage() {
    let dir = tempfile::tempdir().unwrap();
    // run: zero rows at the start, in a gap and at the end; rrun: only two
    // consecutive valid frames, the least a clip may have
    let from = clip_folder(
        dir.path(),
        &[
            (
                "run/013_holes.pt",
                run_clip_zeroed(|r, n| r < 6 || (30..40).contains(&r) || r + 6 >= n),
            ),
            (
                "rrun/012_two.pt",
                run_clip_zeroed(|r, _| r != 40 && r != 41),
            ),
        ],
    );
    let run = dir.path().join("run");
    let r = s(&run);
    let text = ok(&["ingest", "--from", s(&from), "--out", r]);
    assert!(text.contains("ingested 3 clips"), "{text}");
    ok(&["build-stg", "--out", r, "-q"]);
    ok(&[
        "sample-stf",
        "--out",
        r,
        "-q",
        "--set",
        "sample-stf.trajectories=64",
    ]);
    tiny_encoder(r, 3);
    let pol = dir.path().join("pol");
    let mut a = vec![
        "train",
        "--from",
        r,
        "--out",
        s(&pol),
        "-q",
        "--stg",
        "--stf",
        "--ats",
        "--he",
        "--set",
        "train.samples=256",
        "--set",
        "train.warm_start_epochs=2",
    ];
    a.extend_from_slice(TINY_TRAIN);
    ok(&a);
    let ev = dir.path().join("ev");
    eval_quiet(
        r,
        &pol,
        &ev,
        &[
            "--set",
            "eval.trials=3",
            "--set",
            "eval.envs=3",
            "--set",
            "eval.steps=30",
        ],
    );
    assert!(ev.join("eval_summary.parquet").is_file());
}

/// Rewrite the tables of ingested run folder `run` through the library:
/// `edit` changes the clip rows and their frames; the metadata stays.
fn rewrite_tables(
    run: &Path,
    edit: impl Fn(&mut Vec<skillaug::table::clips::ClipRow>, &mut Vec<skillaug::motion::ClipFrames>),
) {
    use skillaug::table::{clips, frames, io};
    let (cp, fp) = (run.join("clips.parquet"), run.join("frames.parquet"));
    let mut rows = clips::read(&cp).unwrap();
    let mut f = frames::read(&fp, &rows).unwrap();
    edit(&mut rows, &mut f);
    let inputs: Vec<frames::ClipInput> = rows
        .iter()
        .zip(&f)
        .map(|(r, fr)| frames::ClipInput {
            clip_id: r.clip_id,
            fps: r.fps as f64,
            frames: fr,
        })
        .collect();
    let mut st = io::Staged::new();
    st.parquet(
        &cp,
        &clips::batch(&rows).unwrap(),
        &io::read_metadata(&cp).unwrap(),
    )
    .unwrap();
    st.parquet(
        &fp,
        &frames::batch(&inputs).unwrap(),
        &io::read_metadata(&fp).unwrap(),
    )
    .unwrap();
    st.commit().unwrap();
}

/// Every stage after ingest on `run` fails, its message holding each of
/// `want`, and writes nothing.
fn later_stages_refuse(dir: &Path, run: &Path, want: &[&str]) {
    let pol = dir.join("pol");
    std::fs::create_dir_all(&pol).unwrap();
    std::fs::write(pol.join("policy.meta.json"), b"{}").unwrap();
    for stage in ["build-stg", "sample-stf", "pretrain-he", "train", "eval"] {
        let out = dir.join(format!("out-{stage}"));
        let mut a = vec![stage, "--from", s(run), "--out", s(&out)];
        if stage == "eval" {
            a.extend(["--policy", s(&pol)]);
        }
        let err = fails(&a);
        for w in want {
            assert!(err.contains(w), "{stage}: `{w}` missing in:\n{err}");
        }
        assert!(!out.exists(), "{stage} left {}", out.display());
    }
}

#[test]
fn tables_holding_an_unusable_clip_are_refused_by_every_later_stage() {
    let dir = tempfile::tempdir().unwrap();
    let from = clip_folder(
        dir.path(),
        &[(
            "run/013_run.pt",
            std::fs::read(data_root().join(GOOD)).unwrap(),
        )],
    );
    let run = dir.path().join("run");
    ok(&["ingest", "--from", s(&from), "--out", s(&run), "-q"]);
    // tables another tool (or an older version) wrote: the run clip empty
    rewrite_tables(&run, |rows, f| {
        let i = rows.iter().position(|r| r.skill == "run").unwrap();
        f[i].valid.iter_mut().for_each(|v| *v = false);
        rows[i].valid_frames = 0;
    });
    later_stages_refuse(
        dir.path(),
        &run,
        &["clip 013_run (skill run)", "no valid frame"],
    );
}

#[test]
fn class_ids_outside_the_condition_or_shared_by_two_skills_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let run_bytes = std::fs::read(data_root().join(GOOD)).unwrap();
    // 099 and 101: two skills beyond the 64 condition slots
    for (name, class) in [("099_a.pt", "99"), ("101_b.pt", "101")] {
        let case = dir.path().join(name);
        let from = clip_folder(&case, &[(&format!("dribble/{name}"), run_bytes.clone())]);
        let err = fails(&["ingest", "--from", s(&from), "--out", s(&case.join("out"))]);
        assert!(
            err.contains(&format!("class id {class} does not fit the 64-slot")),
            "{err}"
        );
        assert!(err.contains(name.trim_end_matches(".pt")), "{err}");
    }
    // one class id for two skills
    let case = dir.path().join("shared");
    let from = clip_folder(
        &case,
        &[
            ("run/013_a.pt", run_bytes.clone()),
            ("walk/013_b.pt", run_bytes.clone()),
        ],
    );
    let err = fails(&["ingest", "--from", s(&from), "--out", s(&case.join("out"))]);
    assert!(
        err.contains("class id 13 is given to two skills, run (clip 013_a) and walk (clip 013_b)"),
        "{err}"
    );
    // tables written elsewhere with class 99: every later stage refuses
    let case = dir.path().join("tables");
    let from = clip_folder(&case, &[("run/013_run.pt", run_bytes)]);
    let run = case.join("run");
    ok(&["ingest", "--from", s(&from), "--out", s(&run), "-q"]);
    rewrite_tables(&run, |rows, _| {
        let i = rows.iter().position(|r| r.skill == "run").unwrap();
        rows[i].class = 99;
    });
    later_stages_refuse(&case, &run, &["clip 013_run (skill run): class id 99"]);
}

#[test]
fn settings_out_of_range_are_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let (_keep, run) = ingested("ballplay");
    let r = s(&run);
    let out = dir.path().join("o");
    let o = s(&out);
    // each command's words, with {r} the run folder and {o} the output
    for (cmd, key) in [
        ("bench sim --set sim.physics_hz=0", "sim.physics_hz = 0"),
        ("bench sim --set sim.physics_hz=inf", "sim.physics_hz = inf"),
        ("bench sim --set sim.substeps=0", "sim.substeps = 0"),
        (
            "bench sim --set sim.ground_restitution=2",
            "sim.ground_restitution = 2",
        ),
        (
            "ingest --dataset ballplay --out {o} --set ingest.fps=-30",
            "ingest.fps = -30",
        ),
        (
            "build-stg --from {r} --out {o} --set build-stg.tau=nan",
            "build-stg.tau = NaN",
        ),
        (
            "sample-stf --from {r} --out {o} --set sample-stf.p_n=1.5",
            "sample-stf.p_n = 1.5",
        ),
        (
            "sample-stf --from {r} --out {o} --set sample-stf.eps.dof=-0.1",
            "sample-stf.eps.dof = -0.1",
        ),
        (
            "pretrain-he --from {r} --out {o} --set pretrain-he.lr=0",
            "pretrain-he.lr = 0",
        ),
        (
            "pretrain-he --from {r} --out {o} --set pretrain-he.kernel=0",
            "pretrain-he.kernel = 0",
        ),
        (
            "train --from {r} --out {o} --set train.ppo.lr=nan",
            "train.ppo.lr = NaN",
        ),
        (
            "train --from {r} --out {o} --set train.ppo.gamma=1.5",
            "train.ppo.gamma = 1.5",
        ),
        (
            "train --from {r} --out {o} --set train.contact_radius=-1",
            "train.contact_radius = -1",
        ),
        (
            "train --from {r} --out {o} --set train.num_envs=0",
            "train.num_envs = 0",
        ),
        (
            "eval --from {r} --out {o} --policy {r} --set eval.trials=0",
            "eval.trials = 0",
        ),
        (
            "eval --from {r} --out {o} --policy {r} --set eval.record=500",
            "eval.record = 500",
        ),
        (
            "eval --from {r} --out {o} --policy {r} --set eval.metrics=[]",
            "eval.metrics = []",
        ),
    ] {
        let cmd = cmd.replace("{r}", r).replace("{o}", o);
        let args: Vec<&str> = cmd.split_whitespace().collect();
        let err = fails(&args);
        assert!(err.contains(key), "{args:?}: `{key}` missing in:\n{err}");
        assert!(!out.exists(), "{args:?} left {}", out.display());
    }
}

#[test]
fn a_second_writer_is_refused_and_tables_of_two_runs_are_not_mixed() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    // another process holds the folder (this test process)
    let lock = skillaug::table::io::OutputLock::acquire(&out, "ingest").unwrap();
    let err = fails(&["ingest", "--dataset", "ballplay", "--out", s(&out)]);
    assert!(
        err.contains("is being written by another skillaug process")
            && err.contains(&format!("pid {}", std::process::id())),
        "{err}"
    );
    assert_eq!(entries(&out), [".skillaug.lock"], "the refused run wrote");
    drop(lock);
    assert!(!out.exists(), "the lock's folder stays after the lock");
    // a lock file left by a killed process blocks nobody
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join(".skillaug.lock"), "skillaug ingest, pid 999999\n").unwrap();
    ok(&["ingest", "--dataset", "ballplay", "--out", s(&out), "-q"]);
    assert!(!out.join(".skillaug.lock").exists());

    // frames.parquet of another ingest run beside clips.parquet
    let other = dir.path().join("other");
    ok(&[
        "ingest",
        "--dataset",
        "ballplay",
        "--out",
        s(&other),
        "-q",
        "--set",
        "ingest.skills=[\"run\"]",
    ]);
    ok(&["build-stg", "--out", s(&out), "-q"]);
    let mixed = dir.path().join("mixed");
    std::fs::create_dir_all(&mixed).unwrap();
    std::fs::copy(out.join("clips.parquet"), mixed.join("clips.parquet")).unwrap();
    std::fs::copy(other.join("frames.parquet"), mixed.join("frames.parquet")).unwrap();
    let err = fails(&["build-stg", "--out", s(&mixed)]);
    assert!(err.contains("come from two different ingest runs"), "{err}");
    // STG edges of another ingest run beside the clips
    std::fs::copy(other.join("clips.parquet"), mixed.join("clips.parquet")).unwrap();
    std::fs::copy(
        out.join("stg_edges.parquet"),
        mixed.join("stg_edges.parquet"),
    )
    .unwrap();
    let err = fails(&["sample-stf", "--out", s(&mixed)]);
    assert!(
        err.contains("stg_edges.parquet was made from the clips of another ingest run"),
        "{err}"
    );
}

/// Permission bits of every file under `dir`, recursively.
fn modes(dir: &Path) -> Vec<(String, u32)> {
    use std::os::unix::fs::PermissionsExt;
    let mut v = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let e = e.unwrap();
        let md = e.metadata().unwrap();
        if md.is_dir() {
            v.extend(modes(&e.path()));
        } else {
            v.push((
                e.path().display().to_string(),
                md.permissions().mode() & 0o777,
            ));
        }
    }
    v
}

#[test]
fn every_output_gets_the_mode_the_umask_implies() {
    let dir = tempfile::tempdir().unwrap();
    for (umask, want) in [("022", 0o644), ("077", 0o600)] {
        let run = dir.path().join(format!("u{umask}"));
        let r = s(&run);
        let pol = run.join("pol");
        let steps = [
            format!("ingest --dataset ballplay --out {r} -q"),
            format!("build-stg --out {r} -q"),
            format!("sample-stf --out {r} -q --set sample-stf.trajectories=8"),
            format!(
                "pretrain-he --out {r} -q --set pretrain-he.steps=2 --set pretrain-he.conv=[8,8,4] \
                 --set pretrain-he.predictor_hidden=[16] --set pretrain-he.batch_size=8"
            ),
            format!(
                "train --from {r} --out {} -q --set train.num_envs=4 --set train.horizon=8 \
                 --set train.ppo.hidden=[16] --set train.ppo.minibatch=16 --set train.samples=32 \
                 --set train.warm_start_epochs=1 --set train.checkpoint_every=1",
                s(&pol)
            ),
        ];
        for st in steps {
            let o = std::process::Command::new("sh")
                .arg("-c")
                .arg(format!(
                    "umask {umask} && exec '{}' {st}",
                    env!("CARGO_BIN_EXE_skillaug")
                ))
                .current_dir(env!("CARGO_MANIFEST_DIR"))
                .env_remove("SKILLAUG_DATA")
                .output()
                .unwrap();
            assert!(
                o.status.success(),
                "{st}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        let m = modes(&run);
        assert!(m.len() >= 15, "{m:?}");
        for (f, mode) in m {
            assert_eq!(mode, want, "{f}: mode {mode:o} under umask {umask}");
        }
    }
}

#[test]
fn a_history_encoder_of_other_clips_in_the_input_folder_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let r = s(&run);
    ok(&["ingest", "--dataset", "ballplay", "--out", r, "-q"]);
    tiny_encoder(r, 2);
    // the folder ingested again with fewer clips: the encoder is stale
    ok(&[
        "ingest",
        "--dataset",
        "ballplay",
        "--out",
        r,
        "-q",
        "--set",
        "ingest.skills=[\"run\", \"lrun\"]",
    ]);
    let pol = dir.path().join("pol");
    let mut a = vec!["train", "--from", r, "--out", s(&pol), "--he"];
    a.extend_from_slice(TINY_TRAIN);
    let err = fails(&a);
    assert!(
        err.contains("he.config.json: the history encoder was pre-trained on other clips"),
        "{err}"
    );
    assert!(!pol.exists());
}
