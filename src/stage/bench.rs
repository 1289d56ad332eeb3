//! `skillaug bench NAME`: benchmarks that print figures (never timed tests).
//!
//! `bench ingest` ingests every shipped dataset (all four manifests, every
//! clip in the data root) into a temporary folder, `--repeat` times, and prints
//! the median wall time per dataset and in total, with the throughput.
//!
//! `bench train` runs whole PPO iterations of `skillaug train` on the
//! Dribble-Forward clips with the CPU preset (128 environments x 32 steps =
//! 4,096 samples per iteration, 256-256 networks, minibatch 2,048) and with
//! the paper's networks (1024-512-512, minibatch 16,384; 512 environments x
//! 32 steps here, the paper's 2,048 being too slow to time on two cores), and prints
//! end-to-end samples per second split into simulation (physics,
//! observation, reward, resets), inference and the PPO update, beside the
//! simulation-only bound measured in the same iterations (samples per
//! second of the environments' steps alone) and the share of it reached.
//!
//! `bench sim` steps the rapier3d humanoid (with the ball and contacts) on
//! one thread and on every thread of the pool, for the full 53-body model
//! and for a 23-body variant without finger bodies, and prints physics
//! steps per second per core and in total, and the scaling. The worlds
//! start from a Dribble-Forward frame and follow its pose with small action
//! noise, reset every 60 policy steps (a training episode) and whenever the
//! root drops below 0.5 m (early termination), so contacts are those of
//! training rather than of a humanoid lying on the ground or standing still.
//! Beside the speed it prints what the settings cost in accuracy
//! ([`crate::sim::checks`]): the PD tracking error with the root held, and,
//! under full-range random actions, the largest speed, the deepest ground
//! penetration and the joint anchor gap. `--set sim.KEY=VALUE` benches other
//! physics settings (the fields of `SimOptions`; training and evaluation use
//! their defaults).

use crate::cli::{Bench, StageArgs};
use crate::motion::state::State;
use crate::sim::mjcf::Model;
use crate::sim::vec_env::VecEnv;
use crate::sim::{ObjectSpec, SimOptions};
use anyhow::{bail, Result};
use std::path::PathBuf;
use std::time::Instant;

/// Datasets `bench ingest` covers.
const DATASETS: [&str; 4] = ["ballplay", "ballplay-m", "locomotion", "parahome"];

/// Run benchmark `what`.
pub fn run(what: Bench, repeat: usize, data_root: Option<PathBuf>, sets: &[String]) -> Result<()> {
    let sets = sets
        .iter()
        .map(|s| crate::config::SetArg::parse_for(s, &["sim"]))
        .collect::<Result<Vec<_>>>()?;
    if what != Bench::Sim && !sets.is_empty() {
        bail!("only `bench sim` takes --set (sim.* keys)");
    }
    let opts: SimOptions = crate::config::resolve(&crate::config::Recipe::default(), "sim", &sets)?;
    match what {
        Bench::Ingest => ingest(repeat.max(1), data_root),
        Bench::Sim => sim(repeat.max(1), data_root, &opts),
        Bench::Train => train(repeat.max(1), data_root),
    }
}

fn stage_args(out: PathBuf, dataset: &str, data_root: Option<PathBuf>) -> StageArgs {
    StageArgs {
        out,
        dataset: Some(dataset.to_string()),
        from: None,
        data_root,
        recipe: None,
        set: Vec::new(),
        seed: 0,
        threads: None,
        quiet: true,
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn ingest(repeat: usize, data_root: Option<PathBuf>) -> Result<()> {
    let tmp = tempfile::tempdir()?;
    let mut totals = vec![0.0; repeat];
    println!(
        "{:<12} {:>8} {:>10} {:>12}",
        "dataset", "frames", "median s", "frames/s"
    );
    let mut all_frames = 0u64;
    for name in DATASETS {
        let out = tmp.path().join(name);
        let mut times = Vec::with_capacity(repeat);
        for total in totals.iter_mut() {
            let args = stage_args(out.clone(), name, data_root.clone());
            let t = Instant::now();
            super::ingest::run(&super::Common::new(args)?, false)?;
            let s = t.elapsed().as_secs_f64();
            times.push(s);
            *total += s;
        }
        let frames = crate::table::io::read_parquet(&out.join("clips.parquet"))?
            .batches
            .iter()
            .map(|b| {
                use arrow::array::AsArray;
                b.column_by_name("frames")
                    .map(|c| {
                        c.as_primitive::<arrow::datatypes::UInt32Type>()
                            .values()
                            .iter()
                            .map(|v| *v as u64)
                            .sum::<u64>()
                    })
                    .unwrap_or(0)
            })
            .sum::<u64>();
        all_frames += frames;
        let m = median(times);
        println!(
            "{name:<12} {frames:>8} {m:>10.3} {:>12.0}",
            frames as f64 / m
        );
    }
    let m = median(totals);
    println!(
        "{:<12} {all_frames:>8} {m:>10.3} {:>12.0}   (median of {repeat}, {} threads)",
        "all",
        all_frames as f64 / m,
        rayon::current_num_threads()
    );
    Ok(())
}

/// Physics steps per second of `worlds` worlds for `policy_steps` steps,
/// run on a pool of `threads` threads.
fn sim_rate(
    model: &Model,
    opts: &SimOptions,
    start: &State,
    threads: usize,
    worlds: usize,
    policy_steps: usize,
) -> Result<f64> {
    use rand::{Rng, SeedableRng};
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    pool.install(|| -> Result<f64> {
        let mut env = VecEnv::new(model, &[ObjectSpec::ball()], opts, worlds)?;
        let a = env.action_dim();
        let base: Vec<f32> = start.joint_rot[..a]
            .iter()
            .map(|v| v / std::f32::consts::PI)
            .collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let t = Instant::now();
        for step in 0..policy_steps {
            if step % 60 == 0 {
                env.for_each(|_, w| w.set_state(start).expect("state fits the model"));
            }
            let actions: Vec<f32> = (0..worlds * a)
                .map(|k| base[k % a] + rng.random_range(-0.1..0.1))
                .collect();
            env.step(&actions);
            // early termination, as in training: a fallen world restarts
            env.for_each(|_, w| {
                if w.root_height() < 0.5 {
                    w.set_state(start).expect("state fits the model");
                }
            });
        }
        let steps = (worlds * policy_steps * opts.substeps) as f64;
        Ok(steps / t.elapsed().as_secs_f64())
    })
}

fn sim(repeat: usize, data_root: Option<PathBuf>, opts: &SimOptions) -> Result<()> {
    let tmp = tempfile::tempdir()?;
    let out = tmp.path().join("ballplay");
    super::ingest::run(
        &super::Common::new(stage_args(out.clone(), "ballplay", data_root.clone()))?,
        false,
    )?;
    let lib = crate::table::load_library(&out)?;
    let root = crate::dataset::data_root(data_root.as_deref())?;
    let full = Model::for_skeleton(&root, lib.skeleton)?;
    let hands = crate::sim::world::hand_bodies(&full);
    let (no_fingers, kept) = full.without(|b| b.parent.is_some_and(|p| hands[p]));
    let run = lib.clips_of("run");
    let clip = run.first().copied().unwrap_or(0);
    let s = lib
        .state(clip, 10)
        .ok_or_else(|| anyhow::anyhow!("frame 10 of the first run clip is missing"))?;
    let threads = rayon::current_num_threads();
    let (worlds, policy_steps) = (16, 240);
    println!(
        "{:<22} {:>6} {:>14} {:>16} {:>8}",
        "model",
        "bodies",
        "1 thread /s",
        format!("{threads} threads /s"),
        "scaling"
    );
    let all_bodies: Vec<usize> = (0..full.bodies.len()).collect();
    for (name, model, bodies) in [
        ("full (with fingers)", &full, &all_bodies),
        ("without fingers", &no_fingers, &kept),
    ] {
        let mut st = s.clone();
        let joints = |v: &[f32]| -> Vec<f32> {
            bodies[1..]
                .iter()
                .flat_map(|&b| v[3 * (b - 1)..3 * b].to_vec())
                .collect()
        };
        st.joint_rot = joints(&s.joint_rot);
        st.joint_vel = joints(&s.joint_vel);
        let mut one = Vec::new();
        let mut all = Vec::new();
        for _ in 0..repeat {
            one.push(sim_rate(model, opts, &st, 1, worlds, policy_steps)?);
            all.push(sim_rate(model, opts, &st, threads, worlds, policy_steps)?);
        }
        let (one, all) = (median(one), median(all));
        println!(
            "{name:<22} {:>6} {one:>14.0} {all:>16.0} {:>7.2}x   ({:.0} steps/s per core)",
            model.bodies.len(),
            all / one,
            all / threads as f64
        );
    }
    println!(
        "physics steps of {worlds} worlds x {policy_steps} policy steps x {} substeps ({} Hz), ball and contacts on; median of {repeat}",
        opts.substeps, opts.physics_hz
    );
    println!("settings: {}", settings_changed(opts)?);
    sim_accuracy(&lib, &full, opts)
}

/// The `[sim]` keys whose values differ from the defaults.
fn settings_changed(opts: &SimOptions) -> Result<String> {
    let now = toml::Table::try_from(opts)?;
    let default = toml::Table::try_from(SimOptions::default())?;
    let changed: Vec<String> = now
        .iter()
        .filter(|(k, v)| default.get(*k) != Some(*v))
        .map(|(k, v)| match v {
            // the options are f32: print them as such, not widened to f64
            toml::Value::Float(f) => format!("sim.{k}={}", *f as f32),
            v => format!("sim.{k}={v}"),
        })
        .collect();
    Ok(if changed.is_empty() {
        "the defaults".to_string()
    } else {
        changed.join(" ")
    })
}

/// What the settings cost in accuracy (`sim::checks`), on the full model:
/// PD tracking from the zero pose to every clip's middle frame with the
/// root held, and 16 worlds under full-range random actions for 5 s.
fn sim_accuracy(lib: &crate::motion::MotionLib, model: &Model, opts: &SimOptions) -> Result<()> {
    use crate::sim::checks;
    let mut errors = Vec::new();
    for c in 0..lib.clips.len() {
        if let Some(target) = lib.state(c, lib.frames[c].frames / 2) {
            errors.push(checks::pd_tracking(model, opts, &target)?);
        }
    }
    let mean = errors.iter().sum::<f32>() / errors.len().max(1) as f32;
    let worst = errors.iter().copied().fold(0f32, f32::max);
    println!(
        "PD tracking, root held, 0.5 s: mean joint error {mean:.2} deg over {} clips (worst {worst:.2})",
        errors.len()
    );
    let starts = checks::spread_starts(lib, 16)?;
    let s = checks::stress(model, opts, &starts, 5.0, 1.0, 7)?;
    println!(
        "random actions, {} worlds x 5 s: finite {}, max speed {:.1} m/s, lowest point {:.3} m ({:?}), joint anchor gap mean {:.2} mm, max {:.1} mm",
        starts.len(),
        s.finite,
        s.max_speed,
        s.lowest.0,
        s.lowest.1,
        1e3 * s.mean_gap,
        1e3 * s.max_gap
    );
    Ok(())
}

fn train(repeat: usize, data_root: Option<PathBuf>) -> Result<()> {
    use super::train::setup;
    use crate::rl::config::{Preset, TrainConfig};
    use crate::rl::trainer::{environment, Timed};
    use crate::rl::{collect, Agent, EpisodeTracker, VecEnv as _};
    use rand::SeedableRng;
    let tmp = tempfile::tempdir()?;
    let out = tmp.path().join("ballplay");
    let common = super::Common::new(stage_args(out.clone(), "ballplay", data_root))?;
    super::ingest::run(&common, false)?;
    println!(
        "{:<26} {:>10} {:>14} {:>9} {:>12} {:>10} {:>13}   ({} threads; medians of {repeat} iterations after one more)",
        "preset",
        "samples/s",
        "sim-only bound",
        "of bound",
        "sim us/samp",
        "act us/samp",
        "update us/samp",
        rayon::current_num_threads()
    );
    for (name, preset, envs) in [
        ("cpu (128 x 32, mb 2048)", Preset::Cpu, None),
        ("paper nets (1024-512-512)", Preset::Paper, Some(512)),
    ] {
        let cfg = TrainConfig {
            skills: vec!["run".into()],
            preset,
            num_envs: envs,
            horizon: Some(32),
            ..TrainConfig::default()
        };
        let s = setup(&common, &cfg)?;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let mut env = environment(&s, &cfg, None, cfg.envs(), &mut rng)?;
        let mut agent = Agent::new(
            env.obs_dim(),
            env.act_dim(),
            &cfg.ppo_config(),
            0,
            &crate::nn::device("cpu")?,
        )?;
        let mut tracker = EpisodeTracker::new(cfg.envs());
        let (mut sim, mut act, mut upd, mut total) = (vec![], vec![], vec![], vec![]);
        // one iteration more than timed: the first warms caches and the allocator
        for i in 0..=repeat {
            let t0 = Instant::now();
            let mut timed = Timed {
                env: &mut env,
                secs: 0.0,
            };
            let ro = collect(&agent, &mut timed, cfg.steps(), &mut tracker, &mut rng)?;
            let sim_s = timed.secs;
            let c = t0.elapsed().as_secs_f64();
            let t1 = Instant::now();
            agent.update(&ro, &mut rng)?;
            if i > 0 {
                upd.push(t1.elapsed().as_secs_f64());
                sim.push(sim_s);
                act.push(c - sim_s);
                total.push(t0.elapsed().as_secs_f64());
            }
        }
        let samples = (cfg.envs() * cfg.steps()) as f64;
        let (sim, act, upd, total) = (median(sim), median(act), median(upd), median(total));
        let us = |x: f64| 1e6 * x / samples;
        // the simulation-only bound: samples/s if the environments' steps
        // (timed inside the same iterations) were all an iteration did
        let bound = samples / sim;
        println!(
            "{name:<26} {:>10.0} {:>14.0} {:>8.0}% {:>12.0} {:>10.0} {:>13.0}",
            samples / total,
            bound,
            100.0 * (samples / total) / bound,
            us(sim),
            us(act),
            us(upd),
        );
    }
    Ok(())
}
