//! `skillaug train` and its environment on the real clips (issue: PPO on the
//! rapier humanoid). Budgets are tiny: these check behaviour, not learning
//! (the learning figures are in the issue notes and `stages/`).

mod common;

use arrow::array::AsArray;
use arrow::datatypes::Float64Type;
use common::*;
use rand::SeedableRng;
use skillaug::cli::StageArgs;
use skillaug::rl::humanoid::{obs_dim, write_observation};
use skillaug::rl::VecEnv;
use skillaug::stage::train::{environment, setup, TrainConfig};
use skillaug::stage::Common;
use std::path::{Path, PathBuf};

/// With [`TINY_TRAIN`]: two mini-epochs, a checkpoint every iteration, two threads.
const TINY: &[&str] = &[
    "--set",
    "train.ppo.epochs=2",
    "--set",
    "train.checkpoint_every=1",
    "--threads",
    "2",
    "-q",
];

fn train_args<'a>(from: &'a str, out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = vec!["train", "--from", from, "--out", out];
    v.extend_from_slice(TINY_TRAIN);
    v.extend_from_slice(TINY);
    v.extend_from_slice(extra);
    v
}

/// Every Float64 column of train_metrics.parquet except the timings.
fn metrics(dir: &Path) -> Vec<(String, Vec<f64>)> {
    let t = skillaug::table::io::read_parquet(&dir.join("train_metrics.parquet")).unwrap();
    let b = &t.batches[0];
    let mut v = Vec::new();
    for f in b.schema().fields() {
        let name = f.name().clone();
        if ["samples_per_s", "sim_s", "act_s", "update_s"].contains(&name.as_str()) {
            continue;
        }
        if let Some(a) = b
            .column_by_name(&name)
            .unwrap()
            .as_primitive_opt::<Float64Type>()
        {
            v.push((name, a.values().to_vec()));
        }
    }
    v
}

fn weights(path: &Path) -> Vec<(String, Vec<f32>)> {
    let m = candle_core::safetensors::load(path, &candle_core::Device::Cpu).unwrap();
    let mut v: Vec<(String, Vec<f32>)> = m
        .into_iter()
        .filter(|(_, t)| t.dtype() == candle_core::DType::F32)
        .map(|(k, t)| (k, t.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

fn checkpoint_iteration(out: &Path) -> Option<u64> {
    let text = std::fs::read_to_string(out.join("checkpoint/state.json")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    v["iteration"].as_u64()
}

#[test]
fn a_run_killed_with_sigkill_and_resumed_matches_the_uninterrupted_run() {
    killed_and_resumed_matches_uninterrupted(false);
}

#[test]
fn a_run_with_the_history_encoder_killed_and_resumed_matches_too() {
    // The encoder embeds the observations of all environments in one batch;
    // the replayed episodes after a resume must still see the same bits.
    killed_and_resumed_matches_uninterrupted(true);
}

fn killed_and_resumed_matches_uninterrupted(he: bool) {
    let (dir, run) = ingested("ballplay");
    let from = run.to_str().unwrap();
    ok(&["build-stg", "--out", from, "-q"]);
    if he {
        tiny_encoder(from, 3);
    }
    // 60 iterations of 32 samples, with every start switch on
    let mut extra = vec![
        "--stf",
        "--stg",
        "--ats",
        "--set",
        "train.samples=1920",
        "--set",
        "train.p_n=0.5",
        "--set",
        "train.p_e=0.5",
        "--seed",
        "7",
    ];
    if he {
        extra.push("--he");
    }
    let a = dir.path().join("a");
    ok(&train_args(from, a.to_str().unwrap(), &extra));
    // the encoder's 3 dimensions are in the observation exactly when asked
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(a.join("policy.meta.json")).unwrap())
            .unwrap();
    assert_eq!(meta["obs_dim"], if he { 905 } else { 902 });

    let b = dir.path().join("b");
    let args = train_args(from, b.to_str().unwrap(), &extra);
    kill_when(
        &args,
        || checkpoint_iteration(&b).is_some_and(|i| i >= 3),
        120,
        "no checkpoint",
    );
    let killed_at = checkpoint_iteration(&b).unwrap();
    assert!(killed_at < 60, "killed after the last iteration");
    assert!(!b.join("policy.safetensors").exists());

    let mut resume = args.clone();
    resume.push("--resume");
    ok(&resume);

    let (ma, mb) = (metrics(&a), metrics(&b));
    assert_eq!(ma.len(), mb.len());
    for ((na, va), (nb, vb)) in ma.iter().zip(&mb) {
        assert_eq!(na, nb);
        assert_eq!(va.len(), 60, "{na}: one row per iteration");
        for (i, (x, y)) in va.iter().zip(vb).enumerate() {
            assert!(
                x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()),
                "{na} differs at iteration {} (killed after {killed_at}): {x} vs {y}",
                i + 1
            );
        }
    }
    let (wa, wb) = (
        weights(&a.join("policy.safetensors")),
        weights(&b.join("policy.safetensors")),
    );
    assert!(!wa.is_empty());
    assert_eq!(wa, wb, "final weights and optimiser moments differ");
    // the switches did something: masked steps, STG and neighbourhood starts
    let get = |n: &str| ma.iter().find(|(k, _)| k == n).unwrap().1.clone();
    let mean = |v: Vec<f64>| {
        let v: Vec<f64> = v.into_iter().filter(|x| !x.is_nan()).collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    assert!(mean(get("stg_start_frac")) > 0.1);
    assert!(mean(get("noised_start_frac")) > 0.1);
    assert!(mean(get("mean_n_masked")) > 0.0);
}

#[test]
fn nsi_starts_are_noised_and_never_masked() {
    let (dir, run) = ingested("ballplay");
    let out = dir.path().join("nsi");
    ok(&train_args(
        run.to_str().unwrap(),
        out.to_str().unwrap(),
        &[
            "--nsi",
            "--set",
            "train.p_n=1.0",
            "--set",
            "train.samples=256",
        ],
    ));
    let m = metrics(&out);
    let get = |n: &str| m.iter().find(|(k, _)| k == n).unwrap().1.clone();
    // NaN: no episode started in that iteration
    let noised = get("noised_start_frac");
    assert!(noised.iter().any(|x| !x.is_nan()));
    assert!(noised.iter().all(|x| x.is_nan() || *x > 0.9), "{noised:?}");
    assert!(get("masked_frac").iter().all(|x| *x == 0.0));
    assert!(get("mean_n_masked").iter().all(|x| x.is_nan() || *x == 0.0));
    assert!(get("mean_sm_reward").iter().all(|x| *x > 0.0 && *x <= 1.0));
    // the default has no noised start at all
    let out2 = dir.path().join("rsi");
    ok(&train_args(
        run.to_str().unwrap(),
        out2.to_str().unwrap(),
        &["--set", "train.samples=64"],
    ));
    let m2 = metrics(&out2);
    let n2 = &m2.iter().find(|(k, _)| k == "noised_start_frac").unwrap().1;
    assert!(n2.iter().all(|x| x.is_nan() || *x == 0.0));
}

#[test]
fn bad_inputs_are_refused_with_what_is_missing() {
    let (dir, run) = ingested("ballplay");
    let from = run.to_str().unwrap();
    let out = dir.path().join("t");
    let o = out.to_str().unwrap();
    let e = fails(&train_args(from, o, &["--stg"]));
    assert!(
        e.contains("stg_edges.parquet") && e.contains("build-stg"),
        "{e}"
    );
    let e = fails(&train_args(from, o, &["--he"]));
    assert!(
        e.contains("he.config.json") && e.contains("pretrain-he"),
        "{e}"
    );
    let e = fails(&train_args(from, o, &["--resume"]));
    assert!(e.contains("no checkpoint"), "{e}");
    let e = fails(&train_args(from, o, &["--set", "train.skills=[\"dunk\"]"]));
    assert!(e.contains("dunk") && e.contains("run"), "{e}");
    let e = fails(&train_args(from, o, &["--method", "xm"]));
    assert!(e.contains("xm"), "{e}");
    let e = fails(&train_args(from, o, &["--set", "train.p_n=2"]));
    assert!(e.contains("p_n"), "{e}");
    // a resume with other settings is refused
    ok(&train_args(from, o, &["--set", "train.samples=32"]));
    let e = fails(&train_args(
        from,
        o,
        &["--set", "train.samples=64", "--resume", "--ats"],
    ));
    assert!(e.contains("settings differ"), "{e}");
    // but a larger budget resumes
    ok(&train_args(
        from,
        o,
        &["--set", "train.samples=64", "--resume"],
    ));
    let m = metrics(&out);
    assert_eq!(m[0].1.len(), 2);
}

#[test]
fn the_history_encoder_adds_three_observation_dimensions() {
    let (dir, run) = ingested("ballplay");
    let from = run.to_str().unwrap();
    tiny_encoder(from, 3);
    let out = dir.path().join("he");
    let mut args = train_args(
        from,
        out.to_str().unwrap(),
        &["--he", "--set", "train.samples=32"],
    );
    args.retain(|a| *a != "-q");
    let text = ok(&args);
    assert!(text.contains("obs 905 act 156"), "{text}");
    let text = ok(&train_args(
        from,
        dir.path().join("plain").to_str().unwrap(),
        &["--set", "train.samples=32"],
    )
    .into_iter()
    .filter(|a| *a != "-q")
    .collect::<Vec<_>>());
    assert!(text.contains("obs 902 act 156"), "{text}");
}

fn common_for(run: &Path, out: PathBuf) -> Common {
    Common::new(StageArgs {
        out,
        dataset: None,
        from: Some(run.to_path_buf()),
        data_root: Some(data_root()),
        recipe: None,
        set: Vec::new(),
        seed: 0,
        threads: None,
        quiet: true,
    })
    .unwrap()
}

#[test]
#[allow(clippy::needless_range_loop)] // several per-env arrays side by side
fn episodes_end_by_falls_below_the_threshold_and_by_their_length() {
    let (dir, run) = ingested("ballplay");
    let common = common_for(&run, dir.path().join("x"));
    let cfg = TrainConfig {
        skills: vec!["run".into(), "layup".into()],
        ..TrainConfig::default()
    };
    let s = setup(&common, &cfg).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let n = 6;
    let mut env = environment(&s, &cfg, None, n, &mut rng).unwrap();
    let od = env.obs_dim();
    assert_eq!(od, obs_dim(s.lib.skeleton, 1, 0));
    assert_eq!(od, 902);
    // zero actions: T-pose targets, the humanoid collapses
    let zeros = vec![0f32; n * env.act_dim()];
    let mut lengths = vec![0usize; n];
    let (mut falls, mut timeouts) = (0, 0);
    for _ in 0..150 {
        let r = env.step(&zeros, &mut rng).unwrap();
        for e in 0..n {
            lengths[e] += 1;
            assert!(
                (0.0..=1.0).contains(&r.rewards[e]),
                "SM reward {}",
                r.rewards[e]
            );
            let root_z = r.final_obs[e * od];
            if r.terminated[e] {
                assert!(root_z < 0.3, "terminated with the root at {root_z} m");
                assert!(lengths[e] > 1);
                falls += 1;
            }
            if r.truncated[e] {
                assert!(root_z >= 0.3 || lengths[e] == 1);
                assert!(lengths[e] <= 60);
                timeouts += 1;
            }
            if r.terminated[e] || r.truncated[e] {
                lengths[e] = 0;
            }
        }
    }
    assert!(falls > 0, "zero actions never fell");
    let st = env.take_stats();
    assert_eq!(st.falls, falls);
    assert_eq!(st.episodes, falls + timeouts);
    eprintln!(
        "zero actions: {falls} falls, {timeouts} timeouts, mean SM {:.3}",
        st.mean_sm()
    );
}

#[test]
fn the_observation_does_not_change_when_the_scene_turns_about_the_vertical() {
    let (dir, run) = ingested("ballplay");
    let common = common_for(&run, dir.path().join("x"));
    let s = setup(&common, &TrainConfig::default()).unwrap();
    let lib = &s.lib;
    let sk = lib.skeleton;
    let mut w = skillaug::sim::World::new(&s.model, &s.objects, &s.sim).unwrap();
    let od = obs_dim(sk, 1, 0);
    for (clip, frame) in [(0, 10), (3, 40)] {
        let st = lib.state(clip, frame).unwrap();
        let turned = skillaug::reward::apply_alignment(&st, 1.1, [0.0, 0.0], [2.0, -1.0]);
        let mut a = vec![0f32; od];
        let mut b = vec![0f32; od];
        w.set_state(&st).unwrap();
        write_observation(&w, &w.get_state(), None, sk, 13, &mut a);
        w.set_state(&turned).unwrap();
        write_observation(&w, &w.get_state(), None, sk, 13, &mut b);
        for (i, (x, y)) in a.iter().zip(&b).enumerate() {
            assert!((x - y).abs() < 2e-3, "entry {i}: {x} vs {y}");
        }
        assert_eq!(a[0], st.root_pos[2]);
        assert_eq!(a[od - 64 + 13], 1.0);
        assert_eq!(a[od - 64..].iter().sum::<f32>(), 1.0);
    }
}

#[test]
fn open_loop_reference_targets_score_above_zero_actions() {
    // The reward pipeline of the environment (post-step state against the
    // next reference frame, contacts from the step) on the Dribble-Forward
    // clips: replaying the next reference pose as PD targets must track
    // better than holding the T-pose targets.
    use skillaug::reward::{self, RewardOptions, Weights};
    let (dir, run) = ingested("ballplay");
    let common = common_for(&run, dir.path().join("x"));
    let s = setup(&common, &TrainConfig::default()).unwrap();
    let lib = &s.lib;
    let sk = lib.skeleton;
    let w8 = Weights::sm(reward::DatasetKind::of_library(lib));
    let score = |open_loop: bool| -> f64 {
        let (mut sum, mut n) = (0.0, 0);
        for clip in lib.clips_of("run") {
            for start in (2..lib.frames[clip].frames - 31).step_by(10) {
                let mut w = skillaug::sim::World::new(&s.model, &s.objects, &s.sim).unwrap();
                w.set_state(&lib.state(clip, start).unwrap()).unwrap();
                let mut prev = w.get_state().joint_vel;
                for t in 1..=30 {
                    let r = lib.state(clip, start + t).unwrap();
                    if open_loop {
                        w.set_joint_targets(&r.joint_rot);
                    } else {
                        w.set_joint_targets(&vec![0.0; r.joint_rot.len()]);
                    }
                    w.step();
                    let g = w.get_state();
                    let c = w.contacts().reward_contacts(sk.contact_penalty_bodies());
                    let opts = RewardOptions::default();
                    sum += reward::sm_reward(&g, &r, &c, sk, &w8, &opts, Some(&prev)).total;
                    prev = g.joint_vel;
                    n += 1;
                }
            }
        }
        sum / n as f64
    };
    let (open, zero) = (score(true), score(false));
    eprintln!("mean SM reward over 30 steps: open loop {open:.3}, zero actions {zero:.3}");
    assert!(open > zero + 0.05, "open loop {open} vs zero {zero}");
}
