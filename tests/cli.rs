//! The command line: help, schema, inspect, recipes and resolved settings.

mod common;

use common::*;
use std::path::Path;

#[test]
fn help_lists_every_subcommand_with_one_line() {
    let out = ok(&["--help"]);
    for cmd in [
        "ingest",
        "build-stg",
        "sample-stf",
        "inspect",
        "schema",
        "bench",
    ] {
        let line = out
            .lines()
            .find(|l| l.trim_start().starts_with(cmd))
            .unwrap_or_else(|| panic!("{cmd} missing from --help:\n{out}"));
        assert!(line.trim().len() > cmd.len() + 10, "no description: {line}");
    }
    let ingest = ok(&["ingest", "--help"]);
    for flag in [
        "--out",
        "--dataset",
        "--from",
        "--seed",
        "--quiet",
        "--set",
        "--recipe",
        "--data-root",
        "--skip-bad",
    ] {
        assert!(ingest.contains(flag), "ingest --help lacks {flag}");
    }
}

#[test]
fn schema_prints_the_golden_files() {
    for table in skillaug::table::Table::ALL {
        let name = table.name();
        let want = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("schemas/{name}.txt")),
        )
        .unwrap();
        assert_eq!(ok(&["schema", name]), want);
    }
    let err = fails(&["schema", "nope"]);
    assert!(err.contains("'nope'") && err.contains("frames"), "{err}");
}

#[test]
fn inspect_summarises_frames_per_skill() {
    let (_dir, out) = ingested("ballplay");
    let s = ok(&["inspect", out.join("frames.parquet").to_str().unwrap()]);
    assert!(s.contains("table     frames"), "{s}");
    assert!(s.contains("clips     6"), "{s}");
    assert!(s.contains("frames    796 (796 valid)"), "{s}");
    assert!(s.contains("skills    5"), "{s}");
    // run = DF: two clips of 81 frames
    let run = s
        .lines()
        .find(|l| l.trim_start().starts_with("run "))
        .unwrap();
    let nums: Vec<&str> = run.split_whitespace().collect();
    assert_eq!(nums[1..4], ["162", "2", "162"], "{run}");
    let root = s.lines().find(|l| l.starts_with("root_pos ")).unwrap();
    assert!(root.contains(".."), "{root}");
    let s = ok(&["inspect", out.join("clips.parquet").to_str().unwrap()]);
    assert!(
        s.contains("table     clips") && s.contains("skills    5"),
        "{s}"
    );
    let err = fails(&[
        "inspect",
        out.join("ingest.resolved.toml").to_str().unwrap(),
    ]);
    assert!(
        err.contains("ingest.resolved.toml") && err.contains("not a Parquet file"),
        "{err}"
    );
}

#[test]
fn resolved_settings_follow_defaults_recipe_set() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = dir.path().join("r.toml");
    std::fs::write(
        &recipe,
        "[ingest]\nangvel_frame = \"world\"\nskills = [\"run\", \"shot\"]\n",
    )
    .unwrap();
    let out = dir.path().join("run");
    let stdout = ok(&[
        "ingest",
        "--dataset",
        "ballplay",
        "--recipe",
        recipe.to_str().unwrap(),
        "--set",
        "ingest.skills=[\"run\"]",
        "--seed",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(stdout.contains("ingested 2 clips"), "{stdout}");
    let text = std::fs::read_to_string(out.join("ingest.resolved.toml")).unwrap();
    let t: toml::Table = text.parse().unwrap();
    let ing = t["ingest"].as_table().unwrap();
    assert_eq!(ing["angvel_frame"].as_str(), Some("world"));
    assert_eq!(ing["skills"].as_array().unwrap().len(), 1);
    assert_eq!(ing["obj_angvel"].as_str(), Some("quat-diff"));
    assert_eq!(t["run"]["seed"].as_integer(), Some(3));
}

#[test]
fn shipped_recipes_resolve() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("stages");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "toml") {
            let r = skillaug::config::Recipe::load(&p).unwrap();
            skillaug::config::resolve::<skillaug::ingest::IngestConfig>(&r, "ingest", &[])
                .unwrap_or_else(|e| panic!("{}: {e:#}", p.display()));
            skillaug::config::resolve::<skillaug::augment::settings::StgConfig>(
                &r,
                "build-stg",
                &[],
            )
            .unwrap_or_else(|e| panic!("{}: {e:#}", p.display()));
            n += 1;
        }
    }
    assert!(n > 0);
}

#[test]
fn bench_settings_are_checked_before_any_work() {
    let err = fails(&["bench", "sim", "--set", "sim.bogus=1"]);
    assert!(err.contains("bogus"), "{err}");
    let err = fails(&["bench", "sim", "--set", "train.samples=1"]);
    assert!(err.contains("unknown stage `train`"), "{err}");
    let err = fails(&["bench", "ingest", "--set", "sim.pgs_iterations=2"]);
    assert!(err.contains("only `bench sim` takes --set"), "{err}");
    let err = fails(&["bench", "sim", "--set", "sim.pgs_iterations=\"two\""]);
    assert!(err.contains("sim.pgs_iterations"), "{err}");
}

#[test]
fn commands_other_than_train_refuse_to_start_as_one_of_several_processes() {
    // what mpirun (OMPI_COMM_WORLD_SIZE) and srun (SLURM_STEP_NUM_TASKS) announce
    for var in ["OMPI_COMM_WORLD_SIZE", "SLURM_STEP_NUM_TASKS"] {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("bp");
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_skillaug"))
            .args(["ingest", "--dataset", "ballplay", "--out"])
            .arg(&out)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .env(var, "2")
            .output()
            .unwrap();
        assert!(!o.status.success());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("one of 2 processes") && err.contains("only `skillaug train`"),
            "{err}"
        );
        assert!(!out.exists(), "nothing is written");
    }
}
