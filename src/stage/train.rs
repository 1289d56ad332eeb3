//! `skillaug train`: PPO on the rapier3d humanoid with the SM or DM reward
//! and every component of the method as a switch (`--nsi --stg --stf --ats
//! --he`), so the baselines and the ablations of Tables 1 and 3 are one
//! program with different recipes. The trainer is [`crate::rl::trainer`];
//! this stage resolves the settings (the `[train]` table, with the
//! `[sample-stf]` table for the start settings), drives the loop with a
//! progress bar and writes the outputs: `train_metrics.parquet` (one row per
//! iteration, `skillaug schema train_metrics`), `policy.safetensors` +
//! `policy.json` + `policy.meta.json`, `train.resolved.toml`, and
//! `checkpoint/` every `checkpoint_every` iterations, from which `--resume`
//! continues exactly. Presets and measured settings: docs/training.md.
//! Started by `mpirun`/`srun` with the `mpi` feature, it runs as one rank of
//! a data-parallel job ([`crate::rl::comm`]; rank 0 writes).

use super::Common;
use crate::rl::comm::Comm;
use crate::rl::config::{Switches, TrainConfig};
use crate::rl::trainer::{history_encoder, Setup, TrainInputs, Trainer};
use crate::table::io::Outputs;
use crate::table::{self, train::MetricRow};
use anyhow::{Context, Result};

/// Stage `train_metrics.parquet` of `rows` into `o`.
fn stage_metrics(o: &mut Outputs, rows: &[MetricRow], resolved: &str, dataset: &str) -> Result<()> {
    let meta = table::Meta::new(dataset, resolved);
    o.parquet(
        "train_metrics.parquet",
        &table::train::batch(rows)?,
        &meta.table("train_metrics"),
    )
}

/// Run the stage.
pub fn run(common: &Common, sw: &Switches) -> Result<()> {
    let comm = crate::rl::comm::world()?;
    let r = run_ranks(common, sw, comm.as_ref());
    if let Err(e) = &r {
        comm.abort_on_error(e);
    }
    r
}

fn run_ranks(common: &Common, sw: &Switches, comm: &dyn Comm) -> Result<()> {
    let mut cfg: TrainConfig = common.settings("train")?;
    sw.apply(&mut cfg);
    let root = comm.is_root();
    let _lock = if root {
        Some(common.lock_output("train")?)
    } else {
        None
    };
    let dev = sw.device.unwrap_or_default().open()?;
    let stf_cfg = common.settings("sample-stf")?;
    let s = Setup::load(
        common.input_dir(),
        common.args.data_root.as_deref(),
        &cfg,
        &stf_cfg,
    )?;
    let (he, he_dir) = match history_encoder(common.input_dir(), &cfg, &s.lib, &dev)? {
        Some((h, d)) => (Some(h), Some(d)),
        None => (None, None),
    };
    let out = common.args.out.clone();
    if root {
        std::fs::create_dir_all(&out)
            .with_context(|| format!("cannot create the output folder {}", out.display()))?;
    }
    let resolved = common.resolved_toml("train", &cfg)?;
    let seed = common.args.seed;
    let quiet = common.args.quiet || !root;
    if !sw.resume {
        crate::rl::trainer::refuse_to_replace(&out)?;
    }
    let inputs = TrainInputs {
        setup: &s,
        cfg: &cfg,
        stf_cfg: &stf_cfg,
        seed,
        dev: &dev,
        comm,
    };
    let mut t = if sw.resume {
        Trainer::resume(inputs, he, &out)?
    } else {
        Trainer::start(inputs, he)?
    };
    if !quiet {
        if let Some(w) = &t.warm_start {
            println!(
                "train: warm start on {} states, {} epochs: action error (mse) {:.4} -> {:.4} ({:.1} s)",
                w.states, cfg.warm_start_epochs, w.mse.0, w.mse.1, w.secs
            );
            for p in &w.pushes {
                print_push("push window", p, &s.lib);
            }
        }
        for p in &t.push_ff {
            print_push("push feed-forward", p, &s.lib);
        }
        for f in &s.flights {
            print_flight(f, &s.lib);
        }
        println!("{}", t.describe(sw.resume));
    }
    let dataset = s.lib.clips[0].dataset.clone();
    let bar = crate::progress::bar(cfg.samples, "train", quiet);
    bar.set_position(t.samples().min(cfg.samples));
    while !t.done() {
        let row = t.iterate()?.clone();
        let m = &row.metrics;
        bar.set_position(row.samples.min(cfg.samples));
        bar.set_message(format!(
            "{:.0} samples/s  reward {:.3}  sm {:.3}  len {:.1}  falls {:.0}%",
            m.samples_per_s,
            m.mean_reward,
            m.mean_sm_reward,
            m.mean_episode_length,
            100.0 * m.fall_rate
        ));
        // without a terminal (logs), one line per iteration instead of the bar
        if !quiet && bar.is_hidden() {
            println!("{}", row.log_line());
        }
        if row.iteration % cfg.checkpoint_every == 0 || t.done() {
            t.checkpoint(&out)?;
            if root {
                let mut o = Outputs::new(&out)?;
                stage_metrics(&mut o, t.metrics(), &resolved, &dataset)?;
                o.commit()?;
            }
        }
    }
    bar.finish_and_clear();
    if !root {
        return Ok(());
    }
    // one commit: the policy, its metrics and its metadata appear together
    let meta = t.policy_meta(&stf_cfg, he_dir);
    let mut o = Outputs::new(&out)?;
    o.with_staged("policy.safetensors", |staged, path| {
        t.agent().stage(staged, path)
    })?;
    stage_metrics(&mut o, t.metrics(), &resolved, &dataset)?;
    o.text("policy.meta.json", &serde_json::to_string_pretty(&meta)?)?;
    o.text("train.resolved.toml", &resolved)?;
    o.commit()?;
    if !quiet {
        if let Some(r) = t.metrics().last() {
            println!(
                "trained {} iterations, {} samples{}: last mean reward {:.4}, SM {:.4}, falls {:.1}%; wrote {}",
                r.iteration,
                r.samples,
                if comm.size() > 1 {
                    format!(
                        " on {} ranks (weights identical on every rank after every update)",
                        comm.size()
                    )
                } else {
                    String::new()
                },
                r.get("mean_reward").unwrap_or(f64::NAN),
                r.get("mean_sm_reward").unwrap_or(f64::NAN),
                100.0 * r.get("fall_rate").unwrap_or(f64::NAN),
                out.join("train_metrics.parquet").display()
            );
        }
    }
    Ok(())
}

/// One simulated reference flight's line (`train.reference_ball`): the
/// clip's release velocity, the solved one, and how far from the clip's
/// ball at the catch frame a ball released with each lands.
fn print_flight(f: &crate::sim::ball_path::Flight, lib: &crate::motion::MotionLib) {
    let h = |v: &[f64; 3]| v[0].hypot(v[1]);
    println!(
        "train: reference ball {} frames {}..{}: released at v_z {:.2} m/s, horizontal {:.2} (clip: {:.2}, {:.2}); at the catch {:.3} m from the clip's ball (released as the clip's: {:.2} m){}",
        lib.clips[f.clip].name,
        f.release,
        f.catch,
        f.v_sim[2],
        h(&f.v_sim),
        f.v_clip[2],
        h(&f.v_clip),
        f.miss_sim,
        f.miss_clip,
        match (f.applied, f.bounces) {
            (true, _) => String::new(),
            (false, 1) => "; not solved, the clip's ball kept".into(),
            (false, n) => format!("; the solution bounces {n} times, the clip's ball kept"),
        }
    );
}

/// One searched push window's line: the ball's vertical velocity at the
/// release with the clip's own targets, with the offset, and the clip's,
/// and their horizontal speeds; then, where the window has a catch frame,
/// the ball's distance there from the clip's (relative to the root) with
/// the clip's own targets and with the offset.
fn print_push(what: &str, p: &crate::sim::push::PushOffset, lib: &crate::motion::MotionLib) {
    println!(
        "train: {what} {} frames {}..{}: ball v_z at release {:.2} m/s with the clip's own targets, {:.2} with the offset (RMS {:.2} rad, largest {:.2}), clip {:.2}; horizontal speed {:.2}, {:.2}, clip {:.2}",
        lib.clips[p.clip].name,
        p.window.start,
        p.window.release,
        p.own.vel[2],
        p.found.vel[2],
        p.found.rms_offset,
        p.found.max_offset,
        p.vel_ref[2],
        p.own.vel[0].hypot(p.own.vel[1]),
        p.found.vel[0].hypot(p.found.vel[1]),
        p.vel_ref[0].hypot(p.vel_ref[1]),
    );
    if let (Some(c), Some(a), Some(b)) = (p.window.catch, p.own.catch_err, p.found.catch_err) {
        println!(
            "train: {what} {} frame {c} (the clip's next catch): the ball {a:.2} m from the clip's, relative to the root, with the clip's own targets, {b:.2} with the offset",
            lib.clips[p.clip].name
        );
    }
}
