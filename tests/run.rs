//! `skillaug run stages/smoke.toml`: the whole pipeline on the real clips
//! with tiny budgets; an interrupted run resumes, a finished one is skipped,
//! a changed setting re-runs its stage and those after it.

mod common;

use common::*;

fn lock_has_started(out: &std::path::Path, key: &str) -> bool {
    std::fs::read_to_string(out.join("run.lock.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .is_some_and(|v| v["steps"][key]["done"] == serde_json::Value::Bool(false))
}

#[test]
fn the_smoke_recipe_runs_resumes_and_skips() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("smoke");
    let o = out.to_str().unwrap();
    let args = ["run", "stages/smoke.toml", "--out", o, "--threads", "2"];
    // start, and kill it while the first policy trains
    kill_when(
        &args,
        || lock_has_started(&out, "train:SM"),
        300,
        "training never started",
    );

    let text = ok(&args);
    for done in [
        "ingest: up to date",
        "pretrain-he: up to date",
        "run: train:SM (resuming)",
    ] {
        assert!(text.contains(done), "missing `{done}` in:\n{text}");
    }
    assert!(
        text.contains("paper: SM+Ours"),
        "the run ends with the report:\n{text}"
    );
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(md.lines().any(|l| l.starts_with("| SM |")), "{md}");
    assert!(md.lines().any(|l| l.starts_with("| SM+Ours |")), "{md}");
    // SM+Ours trained with every component: its starts were not all plain
    let m = skillaug::table::io::read_parquet(&out.join("train/SM+Ours/train_metrics.parquet"))
        .unwrap();
    use arrow::array::AsArray;
    let stg = m.batches[0]
        .column_by_name("stg_start_frac")
        .unwrap()
        .as_primitive::<arrow::datatypes::Float64Type>()
        .values()
        .to_vec();
    assert!(stg.iter().any(|x| *x > 0.0), "{stg:?}");

    let again = ok(&args);
    assert!(again.contains("0 step(s) ran"), "{again}");

    let mut changed = args.to_vec();
    changed.extend(["--set", "eval.trials=4"]);
    let text = ok(&changed);
    assert!(text.contains("train:SM+Ours: up to date"), "{text}");
    assert!(
        text.contains("run: eval:SM\n") && text.contains("run: report\n"),
        "{text}"
    );
    assert!(text.contains("3 step(s) ran"), "{text}");
}
