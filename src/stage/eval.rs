//! `skillaug eval`: success rates of a trained policy ([`crate::eval::evaluator`]:
//! SR, TSR, ε-NSR and NR over trials run in parallel with deterministic
//! actions).
//!
//! Outputs: `eval_trials.parquet` (one row per trial) and
//! `eval_summary.parquet` (one row per cell with 95 % Wilson intervals),
//! `eval_rollouts.parquet` with `--record N`, and a printed table.

use super::Common;
use crate::eval::evaluator::{load_policy, plan_cells, EvalConfig, Evaluator};
use crate::eval::method_label;
use crate::rl::humanoid::HeRuntime;
use crate::rl::trainer::Setup;
use crate::table::io::Outputs;
use crate::table::{self, eval as etable};
use anyhow::Result;
use std::path::Path;

/// Run the stage. `policy` is a `skillaug train` output folder.
pub fn run(common: &Common, policy: &Path) -> Result<()> {
    let cfg: EvalConfig = common.settings("eval")?;
    let _lock = common.lock_output("eval")?;
    let input = common.input_dir();
    let lib = table::load_library(input)?;
    let (meta, agent, he_dir) = load_policy(policy, &lib, input)?;
    let label = if cfg.label.is_empty() {
        method_label(&meta.train)
    } else {
        cfg.label.clone()
    };
    let (cells, warnings) = plan_cells(&cfg, &meta, &lib);
    for w in warnings {
        eprintln!("warning: {w}");
    }
    let dataset = lib.clips[0].dataset.clone();
    let mut tcfg = meta.train.clone();
    tcfg.skills = meta.skills.clone();
    tcfg.stg = false;
    let setup = Setup::from_library(
        lib,
        input,
        common.args.data_root.as_deref(),
        &tcfg,
        &meta.stf,
    )?;
    check_flights(&meta, &setup, policy)?;
    let he = match he_dir {
        Some(dir) => {
            let dev = candle_core::Device::Cpu;
            let enc = crate::nn::he::load(&dir, &dev)?;
            Some(HeRuntime::new(enc, &setup.lib)?)
        }
        None => None,
    };
    let ev = Evaluator {
        base_stf: meta.stf.params()?.0,
        setup,
        train: &meta.train,
        agent: &agent,
        he,
        cfg: &cfg,
    };
    let (rows, recorded) = ev.run_all(&cells, common.args.seed)?;
    let summary = crate::eval::summary::summarise(&label, &rows)?;
    let resolved = common.resolved_toml("eval", &cfg)?;
    let tmeta = table::Meta::new(&dataset, &resolved)
        .with("ingest_id", table::ingest_id(&input.join("clips.parquet"))?)
        .with("label", label.clone())
        .with("policy", policy.display().to_string());
    let mut out = Outputs::new(&common.args.out)?;
    out.parquet(
        "eval_trials.parquet",
        &etable::trials_batch(&label, &rows)?,
        &tmeta.table("eval_trials"),
    )?;
    out.parquet(
        "eval_summary.parquet",
        &etable::summary_batch(&summary)?,
        &tmeta.table("eval_summary"),
    )?;
    if cfg.record > 0 {
        out.parquet(
            "eval_rollouts.parquet",
            &crate::table::rollout::batch(&recorded)?,
            &tmeta.table("eval_rollouts"),
        )?;
    }
    out.text("eval.resolved.toml", &resolved)?;
    out.commit()?;
    if !common.args.quiet {
        println!("{}", crate::eval::summary::render(&summary));
        println!(
            "wrote {}",
            common.args.out.join("eval_summary.parquet").display()
        );
    }
    Ok(())
}

/// With `train.reference_ball = "simulated"`: the flights evaluation has
/// just solved (`setup.flights`) must be those the policy was trained
/// against (`meta.reference_flights`), frames, outcome and release
/// velocity to 1e-9 m/s, so an evaluation never scores a policy against
/// another reference than its training's.
///
/// # Errors
/// A description without flights, or flights that differ, naming the
/// policy's `policy.meta.json` and the clip.
fn check_flights(
    meta: &crate::rl::config::PolicyMeta,
    setup: &Setup,
    policy: &std::path::Path,
) -> Result<()> {
    if meta.train.reference_ball == crate::sim::ball_path::ReferenceBall::Captured {
        return Ok(());
    }
    let mp = policy.join("policy.meta.json");
    if meta.reference_flights.is_empty() {
        anyhow::bail!(
            "{}: train.reference_ball = \"simulated\" but the description holds no \
             reference_flights (keep the file `skillaug train` wrote)",
            mp.display()
        );
    }
    let now = crate::rl::trainer::flight_meta(&setup.flights, &setup.lib);
    let same = |a: &crate::rl::config::FlightMeta, b: &crate::rl::config::FlightMeta| {
        a.clip == b.clip
            && a.release == b.release
            && a.catch == b.catch
            && a.applied == b.applied
            && a.v_sim
                .iter()
                .zip(&b.v_sim)
                .all(|(x, y)| (x - y).abs() <= 1e-9)
    };
    let differs = now
        .iter()
        .zip(&meta.reference_flights)
        .find(|(a, b)| !same(a, b));
    if now.len() != meta.reference_flights.len() || differs.is_some() {
        let first = differs.map_or(String::new(), |(a, b)| {
            format!(
                ": clip `{}` frames {}..{}, trained {:?} m/s, now {:?} m/s",
                b.clip, b.release, b.catch, b.v_sim, a.v_sim
            )
        });
        anyhow::bail!(
            "{}: the reference's simulated ball flights come out otherwise than in training \
             ({} now, {} trained{first}); evaluate with the data, physics and build the policy \
             was trained with",
            mp.display(),
            now.len(),
            meta.reference_flights.len()
        );
    }
    Ok(())
}
