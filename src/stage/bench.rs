//! `skillaug bench NAME`: benchmarks that print figures (never timed tests).
//!
//! `bench ingest` ingests every shipped dataset (all four manifests, every
//! clip in the data root) into a temporary folder, `--repeat` times, and prints
//! the median wall time per dataset and in total, with the throughput.
//!
//! `bench train` times whole PPO iterations of the CPU preset and of the
//! paper's networks on the Dribble-Forward clips ([`crate::rl::bench`]),
//! each with the update on flat buffers, on candle's autograd and
//! overlapped with the next rollout, the networks on `--device`, and
//! prints samples per second beside the simulation-only bound.
//!
//! `bench he` times the history encoder's embedding of one window, at the
//! BallPlay shape (316 channels, 60 frames, the pre-training defaults) with
//! random weights and frames: candle's `conv1d` over a batch of 128 windows
//! (one step of the CPU preset), and the per-position kernel the
//! environments use ([`crate::nn::he_kernel`]) from scratch and on a
//! window moved on by one frame, all 128 windows spread over the pool.
//!
//! `bench sim` prints physics steps per second of the full humanoid and of
//! a variant without finger bodies on one thread and on the pool
//! ([`crate::sim::bench`]), then what the settings cost in accuracy
//! ([`crate::sim::checks::accuracy`]). `--set sim.KEY=VALUE` benches other
//! physics settings (the fields of `SimOptions`; training and evaluation use
//! their defaults).

use crate::cli::{Bench, StageArgs};
use crate::sim::bench::{
    median, settings_changed, sim_rates, state_of_bodies, with_and_without_fingers,
};
use crate::sim::mjcf::Model;
use crate::sim::SimOptions;
use anyhow::{bail, Result};
use std::path::PathBuf;
use std::time::Instant;

/// Datasets `bench ingest` covers.
const DATASETS: [&str; 4] = ["ballplay", "ballplay-m", "locomotion", "parahome"];

/// Run benchmark `what`; `device` holds the networks of `bench train`.
///
/// # Errors
/// `--set` for another benchmark than `sim`, `--device` other than the CPU
/// for another than `train`, missing data, or a failed measurement.
pub fn run(
    what: Bench,
    repeat: usize,
    data_root: Option<PathBuf>,
    sets: &[String],
    device: crate::nn::DeviceName,
) -> Result<()> {
    let sets = sets
        .iter()
        .map(|s| crate::config::SetArg::parse_for(s, &["sim"]))
        .collect::<Result<Vec<_>>>()?;
    if what != Bench::Sim && !sets.is_empty() {
        bail!("only `bench sim` takes --set (sim.* keys)");
    }
    if what != Bench::Train && device != crate::nn::DeviceName::Cpu {
        bail!("only `bench train` takes --device");
    }
    let opts: SimOptions = crate::config::resolve(&crate::config::Recipe::default(), "sim", &sets)?;
    match what {
        Bench::Ingest => ingest(repeat.max(1), data_root),
        Bench::Sim => sim(repeat.max(1), data_root, &opts),
        Bench::Train => train(repeat.max(1), data_root, device),
        Bench::He => he(repeat.max(1)),
    }
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
            let args = StageArgs::for_dataset(out.clone(), name, data_root.clone());
            let t = Instant::now();
            super::ingest::run(&super::Common::new(args)?, false)?;
            let s = t.elapsed().as_secs_f64();
            times.push(s);
            *total += s;
        }
        let frames = crate::table::clips::total_frames(&out.join("clips.parquet"))?;
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

/// BallPlay ingested into a temporary folder (removed with the guard).
fn ballplay(data_root: Option<PathBuf>) -> Result<(tempfile::TempDir, PathBuf)> {
    let tmp = tempfile::tempdir()?;
    let out = tmp.path().join("ballplay");
    let args = StageArgs::for_dataset(out.clone(), "ballplay", data_root);
    super::ingest::run(&super::Common::new(args)?, false)?;
    Ok((tmp, out))
}

fn sim(repeat: usize, data_root: Option<PathBuf>, opts: &SimOptions) -> Result<()> {
    let (_tmp, out) = ballplay(data_root.clone())?;
    let lib = crate::table::load_library(&out)?;
    let root = crate::dataset::data_root(data_root.as_deref())?;
    let full = Model::for_skeleton(&root, lib.skeleton)?;
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
    for (name, model, bodies) in with_and_without_fingers(&full) {
        let st = state_of_bodies(&s, &bodies);
        let (one, all) = sim_rates(&model, opts, &st, threads, worlds, policy_steps, repeat)?;
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
    let a = crate::sim::checks::accuracy(&lib, &full, opts)?;
    println!(
        "PD tracking, root held, 0.5 s: mean joint error {:.2} deg over {} clips (worst {:.2})",
        a.pd_mean_deg, a.clips, a.pd_worst_deg
    );
    let st = &a.stress;
    println!(
        "random actions, {} worlds x 5 s: finite {}, max speed {:.1} m/s, lowest point {:.3} m ({:?}), joint anchor gap mean {:.2} mm, max {:.1} mm",
        a.worlds,
        st.finite,
        st.max_speed,
        st.lowest.0,
        st.lowest.1,
        1e3 * st.mean_gap,
        1e3 * st.max_gap
    );
    Ok(())
}

fn train(repeat: usize, data_root: Option<PathBuf>, device: crate::nn::DeviceName) -> Result<()> {
    use crate::augment::settings::StfConfig;
    use crate::rl::bench::{time_iterations, Timing};
    use crate::rl::config::{Preset, TrainConfig};
    use crate::rl::trainer::Setup;
    let (_tmp, out) = ballplay(data_root.clone())?;
    let dev = device.open()?;
    println!(
        "{:<26} {:>10} {:>14} {:>9} {:>12} {:>10} {:>13}   ({} threads, networks on {device}; medians of {repeat} iterations after one more)",
        "preset",
        "samples/s",
        "sim-only bound",
        "of bound",
        "sim us/samp",
        "act us/samp",
        "update us/samp",
        rayon::current_num_threads()
    );
    // Each preset three times: the update on flat buffers (what training
    // runs on the CPU; autograd elsewhere), on candle's autograd
    // (`Agent::use_autograd`), and with the next rollout collected during
    // the update (`train.overlap_rollout`), so that they compare within one
    // run. The overlapped row's share is of the bound of the preset's first
    // row: while they overlap, the update slows the simulation it shares
    // the cores with, which lowers the bound measured in its own iterations.
    let mut first_bound = f64::NAN;
    for (name, preset, envs, timing) in [
        ("cpu (128 x 32, mb 2048)", Preset::Cpu, None, Timing::Flat),
        (
            "  same, autograd update",
            Preset::Cpu,
            None,
            Timing::Autograd,
        ),
        ("  same, overlapped", Preset::Cpu, None, Timing::Overlapped),
        (
            "paper nets (1024-512-512)",
            Preset::Paper,
            Some(512),
            Timing::Flat,
        ),
        (
            "  same, autograd update",
            Preset::Paper,
            Some(512),
            Timing::Autograd,
        ),
        (
            "  same, overlapped",
            Preset::Paper,
            Some(512),
            Timing::Overlapped,
        ),
    ] {
        let cfg = TrainConfig {
            skills: vec!["run".into()],
            preset,
            num_envs: envs,
            horizon: Some(32),
            ..TrainConfig::default()
        };
        let s = Setup::load(&out, data_root.as_deref(), &cfg, &StfConfig::default())?;
        let t = time_iterations(&s, &cfg, repeat, timing, &dev)?;
        if timing == Timing::Flat {
            first_bound = t.bound();
        }
        let bound = if timing == Timing::Overlapped {
            first_bound
        } else {
            t.bound()
        };
        println!(
            "{name:<26} {:>10.0} {:>14.0} {:>8.0}% {:>12.0} {:>10.0} {:>13.0}",
            t.samples_per_s(),
            bound,
            100.0 * t.samples_per_s() / bound,
            t.us_per_sample(t.sim),
            t.us_per_sample(t.act),
            t.us_per_sample(t.update),
        );
    }
    Ok(())
}

fn he(repeat: usize) -> Result<()> {
    use crate::motion::Skeleton;
    use crate::nn::he::{self, HeConfig, HistoryEncoder};
    use crate::nn::he_kernel::{EncoderCache, EncoderKernel};
    use crate::nn::he_train::HeSettings;
    use crate::nn::Params;
    use candle_core::{Device, Tensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rayon::prelude::*;
    let set = HeSettings::default();
    let c = he::channels(Skeleton::MocapHumanoid, 1);
    let k = set.history;
    let cfg = HeConfig {
        version: 1,
        skeleton: Skeleton::MocapHumanoid.name().into(),
        n_objects: 1,
        channels: c,
        history: k,
        embedding: set.embedding,
        conv: set.conv.clone(),
        kernel: set.kernel,
        predictor_hidden: set.predictor_hidden.clone(),
        condition_slots: crate::motion::library::CONDITION_SLOTS,
        feature_layout: String::new(),
        mean: vec![0.0; c],
        std: vec![1.0; c],
        ingest_id: None,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let enc = HistoryEncoder::new(cfg, &mut Params::default(), &mut rng, &Device::Cpu)?;
    let kern = EncoderKernel::new(&enc)?;
    let envs = 128;
    let steps = 32;
    // one stream of frames per environment, k + steps long
    let streams: Vec<Vec<f32>> = (0..envs)
        .map(|_| {
            (0..(k + steps) * c)
                .map(|_| rng.random_range(-2.0..2.0))
                .collect()
        })
        .collect();
    let window = |e: usize, t: usize| &streams[e][t * c..(t + k) * c];
    let mut candle_us = Vec::with_capacity(repeat);
    let mut full_us = Vec::with_capacity(repeat);
    let mut shifted_us = Vec::with_capacity(repeat);
    for _ in 0..repeat + 1 {
        let flat: Vec<f32> = (0..envs).flat_map(|e| window(e, 0).to_vec()).collect();
        let batch = Tensor::from_vec(flat, (envs, k, c), &Device::Cpu)?;
        let t0 = Instant::now();
        let _ = enc.encode(&batch)?.to_vec2::<f32>()?;
        candle_us.push(t0.elapsed().as_secs_f64() * 1e6 / envs as f64);
        let mut caches = vec![EncoderCache::default(); envs];
        let t0 = Instant::now();
        caches
            .par_iter_mut()
            .enumerate()
            .for_each(|(e, cache)| drop(kern.encode_cached(window(e, 0), cache)));
        full_us.push(t0.elapsed().as_secs_f64() * 1e6 / envs as f64);
        let t0 = Instant::now();
        for t in 1..=steps {
            caches
                .par_iter_mut()
                .enumerate()
                .for_each(|(e, cache)| drop(kern.encode_cached(window(e, t), cache)));
        }
        shifted_us.push(t0.elapsed().as_secs_f64() * 1e6 / (envs * steps) as f64);
    }
    for v in [&mut candle_us, &mut full_us, &mut shifted_us] {
        v.remove(0);
    }
    let shifted = median(shifted_us);
    println!(
        "history encoder, {c} channels x {k} frames, conv {:?}, {envs} windows per call ({} threads; medians of {repeat} after one more)",
        set.conv,
        rayon::current_num_threads()
    );
    println!("{:<44} {:>12}", "embedding of one window", "us");
    println!(
        "{:<44} {:>12.1}",
        "candle conv1d, batch of 128",
        median(candle_us)
    );
    println!(
        "{:<44} {:>12.1}",
        "per-position kernel, from scratch",
        median(full_us)
    );
    println!(
        "{:<44} {:>12.1}   (recomputes {:?} positions per layer)",
        "per-position kernel, window moved one frame",
        shifted,
        kern.recomputed_positions()
    );
    Ok(())
}
