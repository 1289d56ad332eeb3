//! `skillaug run RECIPE`: a whole experiment from one recipe: ingest,
//! build-stg, sample-stf, pretrain-he, then train and eval for each method
//! of `[run] methods`, then report.
//!
//! Folders under `--out`: `data/` (the library and the stage outputs that
//! belong to it), `train/<METHOD>/`, `eval/<METHOD>/`, and `report.md`.
//!
//! `run.lock.json` records, per step, a hash of everything the step depends
//! on: its recipe table with the `--set` overrides, the seed, the data
//! root, the method, and the hash of the step before it (so a change
//! re-runs that step and every step after it). A re-run skips steps whose
//! hash is unchanged and that finished; a step that started but did not
//! finish runs again (training resumes from its checkpoint).

use super::Common;
use crate::cli::StageArgs;
use crate::config::{hash_text, SetArg};
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Settings of the `[run]` recipe table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RunConfig {
    /// Dataset manifest to ingest.
    pub dataset: String,
    /// Steps to run, in this order (a subset of ingest, build-stg,
    /// sample-stf, pretrain-he, train, eval, report).
    pub stages: Vec<String>,
    /// Methods to train and evaluate: "SM", "DM", with "+eNSI", "+STG",
    /// "+STF", "+ATS", "+HE", or "+Ours" (= STG+STF+ATS+HE; no STG on ParaHome).
    pub methods: Vec<String>,
    /// Train one policy per listed skill (ParaHome: one per clip) instead of
    /// one policy for every skill; empty = one policy.
    pub policy_per_skill: Vec<String>,
}

const ORDER: [&str; 7] = [
    "ingest",
    "build-stg",
    "sample-stf",
    "pretrain-he",
    "train",
    "eval",
    "report",
];

impl crate::config::Validate for RunConfig {
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        for s in &self.stages {
            c.holds(ORDER.contains(&s.as_str()), || {
                format!("stages: unknown stage `{s}` (known: {})", ORDER.join(", "))
            })?;
        }
        c.holds(!self.methods.is_empty(), || {
            "methods: give at least one method".into()
        })
    }
}

impl Default for RunConfig {
    fn default() -> Self {
        RunConfig {
            dataset: "ballplay".into(),
            stages: ORDER.iter().map(|s| s.to_string()).collect(),
            methods: vec!["SM".into()],
            policy_per_skill: Vec::new(),
        }
    }
}

/// The switches of a method label.
pub fn parse_method(label: &str, parahome: bool) -> Result<super::train::Switches> {
    use crate::rl::humanoid::Method;
    let mut parts = label.split('+').map(str::trim);
    let method = match parts.next().unwrap_or("").to_ascii_uppercase().as_str() {
        "SM" => Method::Sm,
        "DM" => Method::Dm,
        other => bail!("run.methods: `{label}`: `{other}` is not SM or DM"),
    };
    let mut sw = super::train::Switches {
        method: Some(method),
        ..Default::default()
    };
    for p in parts {
        match p.to_ascii_uppercase().as_str() {
            "ENSI" | "NSI" => sw.nsi = true,
            "STG" => sw.stg = true,
            "STF" => sw.stf = true,
            "ATS" => sw.ats = true,
            "HE" => sw.he = true,
            "OURS" => {
                sw.stg = !parahome;
                sw.stf = true;
                sw.ats = true;
                sw.he = true;
            }
            other => bail!(
                "run.methods: `{label}`: unknown component `{other}` (eNSI, STG, STF, ATS, HE, Ours)"
            ),
        }
    }
    Ok(sw)
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
struct Lock {
    steps: BTreeMap<String, LockEntry>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
struct LockEntry {
    hash: String,
    done: bool,
}

fn write_lock(path: &Path, lock: &Lock) -> Result<()> {
    let mut staged = crate::table::io::Staged::new();
    staged.text(path, &serde_json::to_string_pretty(lock)?)?;
    staged.commit()
}

/// Run the experiment of `recipe` into `args.out`.
pub fn run(recipe: &Path, args: StageArgs) -> Result<()> {
    let common = Common::new(StageArgs {
        recipe: Some(recipe.to_path_buf()),
        ..args.clone()
    })?;
    let cfg: RunConfig = common.settings("run")?;
    let parahome = cfg.dataset == "parahome";
    let methods: Vec<(String, super::train::Switches)> = cfg
        .methods
        .iter()
        .map(|m| Ok((m.clone(), parse_method(m, parahome)?)))
        .collect::<Result<_>>()?;
    let out = args.out.clone();
    let _lock = common.lock_output("run")?;
    let lock_path = out.join("run.lock.json");
    let mut lock: Lock = match std::fs::read(&lock_path) {
        Ok(b) => serde_json::from_slice(&b)
            .with_context(|| format!("{} is not a skillaug run lock", lock_path.display()))?,
        Err(_) => Lock::default(),
    };
    let data = out.join("data");
    let quiet = args.quiet;
    let stage_args = |dir: PathBuf, from: Option<PathBuf>| StageArgs {
        out: dir,
        dataset: from.is_none().then(|| cfg.dataset.clone()),
        from,
        recipe: Some(recipe.to_path_buf()),
        ..args.clone()
    };
    let table_text = |stage: &str| -> String {
        let t = common
            .recipe
            .table
            .get(stage)
            .map(|v| toml::to_string(v).unwrap_or_default())
            .unwrap_or_default();
        let sets: Vec<&str> = common
            .sets
            .iter()
            .filter(|s: &&SetArg| s.path[0] == stage)
            .map(|s| s.raw.as_str())
            .collect();
        format!("[{stage}]\n{t}\nset={sets:?}")
    };
    // the policies: (method index, skill of a per-skill policy)
    let policies: Vec<(usize, Option<String>)> = (0..methods.len())
        .flat_map(|i| {
            if cfg.policy_per_skill.is_empty() {
                vec![(i, None)]
            } else {
                cfg.policy_per_skill
                    .iter()
                    .map(|s| (i, Some(s.clone())))
                    .collect()
            }
        })
        .collect();
    let policy_name = |p: &(usize, Option<String>)| match &p.1 {
        Some(s) => format!("{}/{s}", methods[p.0].0),
        None => methods[p.0].0.clone(),
    };
    // the chain of steps: (key, settings, stage, policy)
    let mut steps: Vec<(String, String, &str, Option<usize>)> = Vec::new();
    for st in ORDER.iter().filter(|s| cfg.stages.iter().any(|x| x == *s)) {
        match *st {
            "train" | "eval" => {
                for (i, p) in policies.iter().enumerate() {
                    // later steps chain the hashes of the earlier ones
                    // (train's settings reach eval through `upstream`)
                    let name = policy_name(p);
                    steps.push((
                        format!("{st}:{name}"),
                        table_text(st) + &format!("\npolicy={name}"),
                        st,
                        Some(i),
                    ));
                }
            }
            "report" => steps.push(("report".into(), cfg.methods.join(","), st, None)),
            _ => steps.push((st.to_string(), table_text(st), st, None)),
        }
    }
    let mut upstream = hash_text(&format!(
        "dataset={} seed={} data_root={:?} stf={}",
        cfg.dataset,
        args.seed,
        args.data_root,
        table_text("sample-stf")
    ));
    let mut ran = 0;
    for (key, text, stage, mi) in steps {
        let hash = hash_text(&format!("{upstream}\n{text}"));
        upstream = hash.clone();
        let prev = lock.steps.get(&key).cloned();
        if prev.as_ref().is_some_and(|p| p.hash == hash && p.done) {
            if !quiet {
                println!("run: {key}: up to date");
            }
            continue;
        }
        let resume = prev.as_ref().is_some_and(|p| p.hash == hash && !p.done);
        lock.steps.insert(
            key.clone(),
            LockEntry {
                hash: hash.clone(),
                done: false,
            },
        );
        write_lock(&lock_path, &lock)?;
        if !quiet {
            println!("run: {key}{}", if resume { " (resuming)" } else { "" });
        }
        let policy = mi.map(|i| &policies[i]);
        let method_dir = |kind: &str| -> PathBuf {
            out.join(kind)
                .join(policy_name(policy.expect("a policy step")))
        };
        let skill_set = |a: &mut StageArgs| {
            if let Some((_, Some(skill))) = policy {
                a.set.push(format!("train.skills=[\"{skill}\"]"));
            }
        };
        match stage {
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
                let mut sw = methods[policy.unwrap().0].1.clone();
                sw.resume = resume && dir.join("checkpoint/state.json").is_file();
                if !sw.resume && dir.exists() {
                    std::fs::remove_dir_all(&dir)?;
                }
                let mut a = stage_args(dir, Some(data.clone()));
                skill_set(&mut a);
                super::train::run(&Common::new(a)?, &sw)?
            }
            "eval" => {
                let trained = method_dir("train");
                let dir = method_dir("eval");
                let mut a = stage_args(dir, Some(data.clone()));
                a.set
                    .push(format!("eval.label={}", methods[policy.unwrap().0].0));
                super::eval::run(&Common::new(a)?, &trained)?
            }
            "report" => {
                let inputs: Vec<PathBuf> = policies
                    .iter()
                    .map(|p| out.join("eval").join(policy_name(p)))
                    .filter(|d| d.join("eval_summary.parquet").is_file())
                    .collect();
                super::report::run(&inputs, true, Some(&out.join("report.md")))?
            }
            other => bail!("run: unknown stage {other}"),
        }
        lock.steps.insert(key, LockEntry { hash, done: true });
        write_lock(&lock_path, &lock)?;
        ran += 1;
    }
    if !quiet {
        println!("run: {ran} step(s) ran; lock {}", lock_path.display());
        if ran == 0 && out.join("report.md").is_file() {
            print!("{}", std::fs::read_to_string(out.join("report.md"))?);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn method_labels_parse_into_switches() {
        let s = parse_method("SM+Ours", false).unwrap();
        assert!(s.stg && s.stf && s.ats && s.he && !s.nsi);
        let p = parse_method("SM+Ours", true).unwrap();
        assert!(!p.stg && p.stf && p.ats && p.he);
        let d = parse_method("DM+eNSI", false).unwrap();
        assert_eq!(d.method, Some(crate::rl::humanoid::Method::Dm));
        assert!(d.nsi && !d.stf);
        assert!(parse_method("XM", false).is_err());
        assert!(parse_method("SM+Magic", false).is_err());
    }
}
