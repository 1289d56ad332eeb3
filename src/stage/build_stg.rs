//! `skillaug build-stg`: the Stitched Trajectory Graph of an ingested run
//! folder (paper Section 4.4, Appendix B.4; reference code:
//! Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/offline_state_search.py`;
//! algorithm in [`crate::augment::stg`]).

use super::Common;
use crate::augment::settings::StgConfig;
use crate::augment::stg;
use crate::motion::Skeleton;
use crate::reward::{DatasetKind, Weights};
use crate::table;
use crate::table::io::Outputs;
use anyhow::{bail, Result};
use std::time::Instant;

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
    let (edges, summary) = stg::build(&lib, &weights, &cfg.params());
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
