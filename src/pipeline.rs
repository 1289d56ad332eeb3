//! The plan of `skillaug run RECIPE`: the `[run]` settings, the chain of
//! steps with their hashes and the lock file that records which finished
//! (method labels are parsed by [`crate::eval::parse_method`]) (the stage `skillaug run` executes the steps).
//!
//! `run.lock.json` records, per step, a hash of everything the step depends
//! on: its recipe table with the `--set` overrides, the seed, the data
//! root, the method, and the hash of the step before it (so a change
//! re-runs that step and every step after it). A re-run skips steps whose
//! hash is unchanged and that finished; a step that started but did not
//! finish runs again (training resumes from its checkpoint).

use crate::config::{hash_text, Recipe, SetArg};
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

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

/// Every step kind, in the order a run takes them.
pub const ORDER: [&str; 7] = [
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

/// `run.lock.json`: per step key, its hash and whether it finished.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Lock {
    steps: BTreeMap<String, LockEntry>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
struct LockEntry {
    hash: String,
    done: bool,
}

/// What a run does with a planned step, given its lock entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Todo {
    /// Same hash, finished: skip.
    UpToDate,
    /// Same hash, started but not finished: run again (training resumes).
    Resume,
    /// New or changed: run from scratch.
    Run,
}

impl Lock {
    /// The lock at `path`, or an empty one when there is none.
    ///
    /// # Errors
    /// When the file exists but is not a run lock.
    pub fn load(path: &Path) -> Result<Lock> {
        match std::fs::read(path) {
            Ok(b) => serde_json::from_slice(&b)
                .with_context(|| format!("{} is not a skillaug run lock", path.display())),
            Err(_) => Ok(Lock::default()),
        }
    }

    /// What to do with step `key` of hash `hash`.
    pub fn todo(&self, key: &str, hash: &str) -> Todo {
        match self.steps.get(key) {
            Some(p) if p.hash == hash && p.done => Todo::UpToDate,
            Some(p) if p.hash == hash => Todo::Resume,
            _ => Todo::Run,
        }
    }

    /// Record step `key` with `hash` as started (`done` false) or finished,
    /// and write the lock to `path` atomically.
    ///
    /// # Errors
    /// When the file cannot be written.
    pub fn record(&mut self, path: &Path, key: &str, hash: &str, done: bool) -> Result<()> {
        self.steps.insert(
            key.to_string(),
            LockEntry {
                hash: hash.to_string(),
                done,
            },
        );
        let mut staged = crate::table::io::Staged::new();
        staged.text(path, &serde_json::to_string_pretty(self)?)?;
        staged.commit()
    }
}

/// One policy of a run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Policy {
    /// Index of its method in `[run] methods`.
    pub method: usize,
    /// The skill of a per-skill policy (`None`: every skill).
    pub skill: Option<String>,
}

/// The policies of `cfg` (one per method, or one per method and listed
/// skill).
pub fn policies(cfg: &RunConfig) -> Vec<Policy> {
    (0..cfg.methods.len())
        .flat_map(|i| {
            if cfg.policy_per_skill.is_empty() {
                vec![Policy {
                    method: i,
                    skill: None,
                }]
            } else {
                cfg.policy_per_skill
                    .iter()
                    .map(|s| Policy {
                        method: i,
                        skill: Some(s.clone()),
                    })
                    .collect()
            }
        })
        .collect()
}

/// A policy's folder name under `train/` and `eval/`: its method label,
/// then `/SKILL` for a per-skill policy.
pub fn policy_name(cfg: &RunConfig, p: &Policy) -> String {
    match &p.skill {
        Some(s) => format!("{}/{s}", cfg.methods[p.method]),
        None => cfg.methods[p.method].clone(),
    }
}

/// One step of a run's chain.
#[derive(Clone, Debug)]
pub struct Step {
    /// Lock key: the stage, with `:POLICY` for train and eval.
    pub key: String,
    /// Its hash: the settings it depends on chained to the step before.
    pub hash: String,
    /// The stage (one of [`ORDER`]).
    pub stage: &'static str,
    /// Index into [`policies`] for train and eval.
    pub policy: Option<usize>,
}

/// The chain of `cfg`'s steps in [`ORDER`] with their hashes; `table_text`
/// gives a stage's recipe table with its `--set` overrides as text, and
/// `first` the hash the chain starts from (dataset, seed, data root, STF
/// settings).
pub fn plan(cfg: &RunConfig, table_text: impl Fn(&str) -> String, first: String) -> Vec<Step> {
    let policies = policies(cfg);
    let mut upstream = first;
    let mut steps = Vec::new();
    let mut push = |key: String, text: String, stage: &'static str, policy| {
        let hash = hash_text(&format!("{upstream}\n{text}"));
        upstream = hash.clone();
        steps.push(Step {
            key,
            hash,
            stage,
            policy,
        });
    };
    for st in ORDER.iter().filter(|s| cfg.stages.iter().any(|x| x == *s)) {
        match *st {
            "train" | "eval" => {
                for (i, p) in policies.iter().enumerate() {
                    // later steps chain the hashes of the earlier ones
                    // (train's settings reach eval through `upstream`)
                    let name = policy_name(cfg, p);
                    let text = table_text(st) + &format!("\npolicy={name}");
                    push(format!("{st}:{name}"), text, st, Some(i));
                }
            }
            "report" => push("report".into(), cfg.methods.join(","), st, None),
            _ => push(st.to_string(), table_text(st), st, None),
        }
    }
    steps
}

/// The text of `stage`'s recipe table that its step's hash covers: the
/// table as TOML, then the `--set` overrides of `sets` for that stage.
pub fn table_text(recipe: &Recipe, sets: &[SetArg], stage: &str) -> String {
    let t = recipe
        .table
        .get(stage)
        .map(|v| toml::to_string(v).unwrap_or_default())
        .unwrap_or_default();
    let sets: Vec<&str> = sets
        .iter()
        .filter(|s| s.path[0] == stage)
        .map(|s| s.raw.as_str())
        .collect();
    format!("[{stage}]\n{t}\nset={sets:?}")
}

/// The steps of `cfg` ([`plan`]) with the hashes of the recipe `recipe`
/// with overrides `sets`, seed `seed` and data root `data_root`
/// (`--data-root`): the chain starts from the hash of the dataset, the
/// seed, the data root and the `[sample-stf]` table (which the trainer's
/// starts read too).
pub fn hashed_plan(
    cfg: &RunConfig,
    recipe: &Recipe,
    sets: &[SetArg],
    seed: u64,
    data_root: Option<&Path>,
) -> Vec<Step> {
    let first = hash_text(&format!(
        "dataset={} seed={} data_root={:?} stf={}",
        cfg.dataset,
        seed,
        data_root,
        table_text(recipe, sets, "sample-stf")
    ));
    plan(cfg, |stage| table_text(recipe, sets, stage), first)
}
