//! Thin glue, one file per subcommand: read inputs, call the library, write
//! outputs, print a summary.

pub mod bench;
pub mod build_stg;
pub mod check_ball;
pub mod check_contact;
pub mod check_fk;
pub mod eval;
pub mod export;
pub mod ingest;
pub mod inspect;
pub mod plot;
pub mod pretrain_he;
pub mod report;
pub mod run;
pub mod sample_stf;
pub mod schema;
pub mod seams;
pub mod train;
pub mod view;

use crate::cli::StageArgs;
use crate::config::{self, Recipe, SetArg};
use anyhow::Result;
use serde::{de::DeserializeOwned, Serialize};
use std::path::Path;

/// What every stage gets: its common arguments, the recipe and the overrides.
pub struct Common {
    /// The parsed common flags.
    pub args: StageArgs,
    /// The recipe (empty without `--recipe`).
    pub recipe: Recipe,
    /// `--set` overrides.
    pub sets: Vec<SetArg>,
}

impl Common {
    /// Parse the recipe and overrides, and size the thread pool.
    pub fn new(args: StageArgs) -> Result<Common> {
        if let Some(n) = args.threads {
            // Ignore the error of a second initialisation (tests call stages twice).
            let _ = rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build_global();
            // candle's CPU matmul splits its work for RAYON_NUM_THREADS, else
            // for every physical core (candle-core `src/utils.rs`,
            // `get_num_threads`), whatever the pool holds: with `--threads 1`
            // per MPI rank on two cores it split for two and the PPO update
            // ran 3.5 times slower (docs/training.md, "Data-parallel
            // training"). Written once, when the first stage of the process
            // starts (before the pool's threads run anything); `skillaug run`
            // creates a stage per step with the same value.
            let v = n.to_string();
            if std::env::var("RAYON_NUM_THREADS").ok().as_deref() != Some(v.as_str()) {
                std::env::set_var("RAYON_NUM_THREADS", v);
            }
        }
        let recipe = match &args.recipe {
            Some(p) => Recipe::load(p)?,
            None => Recipe::default(),
        };
        let sets = args
            .set
            .iter()
            .map(|s| s.parse())
            .collect::<Result<Vec<SetArg>>>()?;
        Ok(Common { args, recipe, sets })
    }

    /// The run folder a later stage reads its inputs from: `--from DIR` if
    /// given, else `--out`.
    pub fn input_dir(&self) -> &Path {
        self.args.from.as_deref().unwrap_or(&self.args.out)
    }

    /// The clips `--dataset` or `--from` select ([`crate::ingest::clip_set`]).
    pub fn clip_set(&self, cfg: &crate::ingest::IngestConfig) -> Result<crate::dataset::ClipSet> {
        let a = &self.args;
        crate::ingest::clip_set(
            a.dataset.as_deref(),
            a.from.as_deref(),
            a.data_root.as_deref(),
            cfg,
        )
    }

    /// Lock the output folder (`--out`) for `stage` until the guard drops
    /// ([`crate::table::io::OutputLock`]).
    pub fn lock_output(&self, stage: &str) -> Result<crate::table::io::OutputLock> {
        crate::table::io::OutputLock::acquire(&self.args.out, stage)
    }

    /// The resolved settings of `stage`.
    pub fn settings<T: Serialize + DeserializeOwned + Default + config::Validate>(
        &self,
        stage: &str,
    ) -> Result<T> {
        config::resolve(&self.recipe, stage, &self.sets)
    }

    /// The text of `<stage>.resolved.toml`.
    pub fn resolved_toml<T: Serialize>(&self, stage: &str, settings: &T) -> Result<String> {
        let a = &self.args;
        let mut t = toml::Table::new();
        t.insert("version".into(), env!("CARGO_PKG_VERSION").into());
        t.insert("seed".into(), toml::Value::Integer(a.seed as i64));
        if let Some(d) = &a.dataset {
            t.insert("dataset".into(), d.clone().into());
        }
        if let Some(f) = &a.from {
            t.insert("from".into(), f.display().to_string().into());
        }
        if let Some(r) = &a.recipe {
            t.insert("recipe".into(), r.display().to_string().into());
        }
        let sets: Vec<toml::Value> = a.set.iter().map(|s| s.clone().into()).collect();
        t.insert("set".into(), toml::Value::Array(sets));
        config::resolved_toml(stage, settings, &t)
    }
}
