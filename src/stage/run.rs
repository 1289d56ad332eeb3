//! `skillaug run RECIPE`: a whole experiment from one recipe: ingest,
//! build-stg, sample-stf, pretrain-he, then train and eval for each method
//! of `[run] methods`, then report; the plan, its hashes and the lock file
//! are [`crate::pipeline`].
//!
//! Folders under `--out`: `data/` (the library and the stage outputs that
//! belong to it), `train/<METHOD>/`, `eval/<METHOD>/`, and `report.md`.

use super::Common;
use crate::cli::StageArgs;
use crate::pipeline::{hashed_plan, policies, policy_name, Lock, RunConfig, Todo};
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};

/// Run the experiment of `recipe` into `args.out`.
pub fn run(recipe: &Path, args: StageArgs) -> Result<()> {
    let common = Common::new(StageArgs {
        recipe: Some(recipe.to_path_buf()),
        ..args.clone()
    })?;
    let cfg: RunConfig = common.settings("run")?;
    let parahome = cfg.dataset == "parahome";
    let switches = cfg
        .methods
        .iter()
        .map(|m| crate::eval::parse_method(m, parahome))
        .collect::<Result<Vec<_>>>()?;
    let out = args.out.clone();
    let _lock = common.lock_output("run")?;
    let lock_path = out.join("run.lock.json");
    let mut lock = Lock::load(&lock_path)?;
    let data = out.join("data");
    let quiet = args.quiet;
    let stage_args = |dir: PathBuf, from: Option<PathBuf>| StageArgs {
        out: dir,
        dataset: from.is_none().then(|| cfg.dataset.clone()),
        from,
        recipe: Some(recipe.to_path_buf()),
        ..args.clone()
    };
    let policies = policies(&cfg);
    let steps = hashed_plan(
        &cfg,
        &common.recipe,
        &common.sets,
        args.seed,
        args.data_root.as_deref(),
    );
    let mut ran = 0;
    for step in steps {
        let (key, hash, mi) = (&step.key, &step.hash, step.policy);
        let todo = lock.todo(key, hash);
        if todo == Todo::UpToDate {
            if !quiet {
                println!("run: {key}: up to date");
            }
            continue;
        }
        let resume = todo == Todo::Resume;
        lock.record(&lock_path, key, hash, false)?;
        if !quiet {
            println!("run: {key}{}", if resume { " (resuming)" } else { "" });
        }
        let policy = mi.map(|i| &policies[i]);
        let method_dir = |kind: &str| -> PathBuf {
            out.join(kind)
                .join(policy_name(&cfg, policy.expect("a policy step")))
        };
        let skill_set = |a: &mut StageArgs| {
            if let Some(crate::pipeline::Policy {
                skill: Some(skill), ..
            }) = policy
            {
                a.set.push(format!("train.skills=[\"{skill}\"]"));
            }
        };
        match step.stage {
            "ingest" => super::ingest::run(&Common::new(stage_args(data.clone(), None))?, false)?,
            "build-stg" => super::build_stg::run(
                &Common::new(stage_args(data.clone(), Some(data.clone())))?,
                false,
            )?,
            "sample-stf" => {
                super::sample_stf::run(&Common::new(stage_args(data.clone(), Some(data.clone())))?)?
            }
            "pretrain-he" => super::pretrain_he::run(
                &Common::new(stage_args(data.clone(), Some(data.clone())))?,
                None,
            )?,
            "train" => {
                let dir = method_dir("train");
                let mut sw = switches[policy.unwrap().method].clone();
                sw.resume = resume && dir.join("checkpoint/state.json").is_file();
                if !sw.resume && dir.exists() {
                    std::fs::remove_dir_all(&dir).with_context(|| {
                        format!("cannot remove {} for a fresh training", dir.display())
                    })?;
                }
                let mut a = stage_args(dir, Some(data.clone()));
                skill_set(&mut a);
                super::train::run(&Common::new(a)?, &sw)?
            }
            "eval" => {
                let trained = method_dir("train");
                let dir = method_dir("eval");
                let mut a = stage_args(dir, Some(data.clone()));
                a.set.push(format!(
                    "eval.label={}",
                    cfg.methods[policy.unwrap().method]
                ));
                super::eval::run(&Common::new(a)?, &trained)?
            }
            "report" => {
                let inputs: Vec<PathBuf> = policies
                    .iter()
                    .map(|p| out.join("eval").join(policy_name(&cfg, p)))
                    .filter(|d| d.join("eval_summary.parquet").is_file())
                    .collect();
                super::report::run(&inputs, true, Some(&out.join("report.md")))?
            }
            other => bail!("run: unknown stage {other}"),
        }
        lock.record(&lock_path, key, hash, true)?;
        ran += 1;
    }
    if !quiet {
        println!("run: {ran} step(s) ran; lock {}", lock_path.display());
        if ran == 0 && out.join("report.md").is_file() {
            let report = out.join("report.md");
            let text = std::fs::read_to_string(&report)
                .with_context(|| format!("cannot read {}", report.display()))?;
            print!("{text}");
        }
    }
    Ok(())
}
