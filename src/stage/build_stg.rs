//! `skillaug build-stg`: the Stitched Trajectory Graph of an ingested run
//! folder (paper Section 4.4, Appendix B.4; reference code:
//! Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/offline_state_search.py`;
//! algorithm in [`crate::augment::stg`]).

use super::{Common, Outputs};
use crate::augment::stg::{self, StgParams};
use crate::augment::MaskRule;
use crate::motion::Skeleton;
use crate::reward::{Align, DatasetKind, Weights};
use crate::table;
use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Settings of the `[build-stg]` recipe table.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StgConfig {
    /// Similarity threshold tau (Table 7).
    pub tau: f64,
    /// Maximum masked states N_max (Table 7).
    pub n_max: u32,
    /// Eq. 20 as printed ("paper", ceil) or the reference code's floor rule ("reference").
    pub mask_rule: MaskRule,
    /// Align the start state's heading too, not only its root x, y (reference code; paper: x, y only).
    pub align_yaw: bool,
    /// The reference code's direction: for each frame of A, the best state of each other skill.
    pub per_target: bool,
}

impl crate::config::Validate for StgConfig {
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.range("tau", self.tau, 0.0, 1.0)?;
        c.count("n_max", self.n_max as u64, 0, 10_000)
    }
}

impl Default for StgConfig {
    fn default() -> Self {
        StgConfig {
            tau: 1e-10,
            n_max: 10,
            mask_rule: MaskRule::Paper,
            align_yaw: true,
            per_target: false,
        }
    }
}

/// Run the stage.
pub fn run(common: &Common, per_target_flag: bool) -> Result<()> {
    let started = Instant::now();
    let mut cfg: StgConfig = common.settings("build-stg")?;
    cfg.per_target |= per_target_flag;
    let _lock = common.lock_output("build-stg")?;
    let lib = table::load_library(common.input_dir())?;
    if lib.skeleton == Skeleton::ParaHome {
        bail!(
            "build-stg: {} holds ParaHome clips; the paper builds no Stitched Trajectory Graph for \
             ParaHome (one policy per clip, Section 5.3): train those with STF only",
            common.input_dir().display()
        );
    }
    if lib.skills().len() < 2 {
        bail!(
            "build-stg needs clips of at least two skills; {} has one",
            common.input_dir().display()
        );
    }
    let kind = DatasetKind::of_library(&lib);
    let weights = Weights::sm(kind);
    let params = StgParams {
        tau: cfg.tau,
        n_max: cfg.n_max,
        mask_rule: cfg.mask_rule,
        align: Align {
            xy: true,
            yaw: cfg.align_yaw,
        },
        per_target: cfg.per_target,
    };
    let (edges, summary) = stg::build(&lib, &weights, &params);
    let secs = started.elapsed().as_secs_f64();

    let resolved = common.resolved_toml("build-stg", &cfg)?;
    let meta = table::Meta::new(&lib.clips[0].dataset, &resolved)
        .with(
            "ingest_id",
            table::ingest_id(&common.input_dir().join("clips.parquet"))?,
        )
        .with(
            "direction",
            if cfg.per_target {
                "per-target"
            } else {
                "paper"
            },
        )
        .with("weights", serde_json::to_string(&weights)?);
    let mut out = Outputs::new(&common.args.out)?;
    out.parquet(
        "stg_edges.parquet",
        &table::stg::batch(&edges)?,
        &meta.table("stg_edges"),
    )?;
    out.parquet(
        "stg_summary.parquet",
        &table::stg::summary_batch(&summary)?,
        &meta.table("stg_summary"),
    )?;
    out.text("build-stg.resolved.toml", &resolved)?;
    out.commit()?;

    if !common.args.quiet {
        println!(
            "{:<14} {:>7} {:>6} {:>8} {:>11}  N histogram 0..{}",
            "target skill", "states", "kept", "dropped", "median beta", cfg.n_max
        );
        for s in &summary {
            let hist: Vec<String> = s.n_hist.iter().map(|n| n.to_string()).collect();
            println!(
                "{:<14} {:>7} {:>6} {:>8} {:>11}  {}",
                s.target_skill,
                s.states,
                s.kept,
                s.dropped,
                s.beta_median.map_or("-".into(), |b| format!("{b:.2e}")),
                hist.join(" ")
            );
        }
        println!(
            "built {} edges over {} skills into {} in {secs:.2} s",
            edges.len(),
            summary.len(),
            common.args.out.join("stg_edges.parquet").display()
        );
    }
    Ok(())
}
