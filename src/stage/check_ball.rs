//! `skillaug check-ball`: can the clips' own motion keep their ball? Every
//! clip with a ball (an ingested run folder, `--from`) is replayed with the
//! humanoid set to each frame in turn while the ball is simulated from the
//! first RSI start frame on ([`crate::sim::checks::ball_replays`]), once with the
//! humanoid's bodies dynamic (the ball pushes back on the hands, as in
//! training) and once kinematic (an infinitely strong body). It prints how
//! far the simulated ball ends from the clip's and how hard it hits the
//! floor at its first bounce and how high it rises after it, beside the
//! clip's own figures.
//!
//! With `--set check-ball.push_search=true` it then searches, for every
//! push window of every ball clip, PD target offsets on the arms and on
//! the upper body that bring the ball's release velocity to the clip's
//! ([`crate::sim::push`]), and prints the vertical release velocity of the
//! clip, of the PD replay of its own targets and of the two searches, with
//! the size of the offsets found.
//!
//! With `--set 'check-ball.reference_hand="on-ball"'` every ball clip's
//! pushing hand is first put on top of its ball as `train.reference_hand`
//! does ([`crate::sim::hand_path`]); the command prints each push window's
//! repair (the body held, the largest shift, the inverse kinematics'
//! residual), and the replays and the search run on the repaired clips.
//!
//! `--set check-ball.physics.KEY=VALUE` runs both under other physics
//! ([`crate::sim::checks::ReplayPhysics`]: more physics steps or solver
//! iterations, scaled PD gains, another object density, a ball with a
//! shell's inertia, another angular damping, contact recycling off), to
//! ask whether the simulation set-up is what keeps the clips' motion from
//! pushing their ball.

use super::Common;
use crate::sim::checks::ball_replays;
use crate::sim::hand_path::{repair_hands, ReferenceHand, BLEND_S};
use crate::sim::mjcf::Model;
use crate::sim::push::{fit_pushes, PushConfig, PushSearch};
use anyhow::{bail, Result};

fn opt(x: Option<f64>) -> String {
    x.map_or_else(|| "-".to_string(), |v| format!("{v:.2}"))
}

/// Run the command: print the table (and the push search's, when on).
pub fn run(common: &Common) -> Result<()> {
    let cfg: PushConfig = common.settings("check-ball")?;
    let mut lib = crate::table::load_library(common.input_dir())?;
    let root = crate::dataset::data_root(common.args.data_root.as_deref())?;
    let model = Model::for_skeleton(&root, lib.skeleton)?;
    if cfg.reference_hand == ReferenceHand::OnBall {
        let clips: Vec<usize> = (0..lib.clips.len()).collect();
        let repairs = repair_hands(
            &mut lib,
            &clips,
            &model,
            cfg.hand_radius,
            cfg.min_frames,
            BLEND_S,
        )?;
        println!("reference_hand = \"on-ball\": each push window's hand put on top of its ball");
        println!(
            "{:<34} {:>9}  {:>4}  {:>10}  {:>15}  {:>11}",
            "clip", "frames", "hand", "body", "largest shift m", "residual m"
        );
        for r in &repairs {
            println!(
                "{:<34} {:>4}-{:<4}  {:>4}  {:>10}  {:>15.3}  {:>11.4}",
                lib.clips[r.clip].name,
                r.start,
                r.release,
                r.side,
                model.bodies[r.body].name,
                r.shift,
                r.residual
            );
        }
        println!();
    }
    let found = ball_replays(&lib, &model, &root, &cfg.physics)?;
    if found.is_empty() {
        bail!(
            "check-ball: no clip in {} has an object",
            common.input_dir().display()
        );
    }
    println!(
        "{:<34} {:>5}  {:>17}  {:>17}  {:>23}  {:>20}",
        "clip",
        "steps",
        "error mean (d/k) m",
        "error 0.5 s (d/k)",
        "impact ref/d/k m/s",
        "apex ref/d/k m"
    );
    for (c, d, k) in &found {
        println!(
            "{:<34} {:>5}  {:>8.2} {:>8.2}  {:>8.2} {:>8.2}  {:>7} {:>7} {:>7}  {:>6} {:>6} {:>6}",
            lib.clips[*c].name,
            d.steps,
            d.err_mean,
            k.err_mean,
            d.err_half_s,
            k.err_half_s,
            opt(d.impact_ref),
            opt(d.impact_sim),
            opt(k.impact_sim),
            opt(d.apex_ref),
            opt(d.apex_sim),
            opt(k.apex_sim),
        );
    }
    println!("d: dynamic humanoid (the ball pushes back); k: kinematic humanoid (it does not)");
    if cfg.push_search {
        print_push_search(&lib, &model, &root, &cfg, common.args.seed)?;
    }
    Ok(())
}

fn print_push_search(
    lib: &crate::motion::MotionLib,
    model: &Model,
    root: &std::path::Path,
    cfg: &PushConfig,
    seed: u64,
) -> Result<()> {
    let fits = fit_pushes(lib, model, root, cfg, seed)?;
    println!();
    println!(
        "push windows: ball v_z at the release, m/s (speed error |v - v_ref|), under PD from the window's first frame"
    );
    println!(
        "{:<34} {:>9}  {:>6}  {:>13}  {:>13}  {:>13}  {:>13}  {:>11}  {:>11}",
        "clip",
        "frames",
        "clip",
        "own targets",
        "+ velocities",
        "arms",
        "upper body",
        "arms rad",
        "upper rad"
    );
    for p in &fits {
        let err = |v: &[f64; 3]| -> f64 {
            (0..3)
                .map(|k| (v[k] - p.vel_ref[k]).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        let cell = |v: &[f64; 3]| format!("{:6.2} ({:4.2})", v[2], err(v));
        println!(
            "{:<34} {:>4}-{:<4}  {:>6.2}  {:>13}  {:>13}  {:>13}  {:>13}  {:>4.2} / {:>4.2}  {:>4.2} / {:>4.2}",
            lib.clips[p.clip].name,
            p.window.start,
            p.window.release,
            p.vel_ref[2],
            cell(&p.replay.vel),
            cell(&p.replay_rates.vel),
            cell(&p.arms.vel),
            cell(&p.upper.vel),
            p.arms.rms_offset,
            p.arms.max_offset,
            p.upper.rms_offset,
            p.upper.max_offset,
        );
    }
    println!(
        "+ velocities: own targets with the clip's joint velocities as target velocities (train.velocity_feed_forward); offsets: RMS / largest over the searched axes; arms: shoulders, elbows, wrists; upper body: also torso, spine, chest, thorax, neck"
    );
    println!();
    println!(
        "push windows: SM reward summed over the window and up to {} frames after it (the clip's own targets after the release), and its factors' means r_b / r_o / r_rel / r_cg; the search's objective: {}",
        cfg.sm_frames,
        match cfg.objective {
            crate::sim::push::PushObjective::Ball => "the ball at the release",
            crate::sim::push::PushObjective::Sm => "this SM sum",
            crate::sim::push::PushObjective::Catch => "the ball at the catch",
        }
    );
    println!(
        "{:<34} {:>9}  {:>5}  {:>30}  {:>30}  {:>30}",
        "clip", "frames", "steps", "own targets", "arms", "upper body"
    );
    for p in &fits {
        let cell = |s: &PushSearch| match s.sm {
            Some(m) => format!(
                "{:6.2} ({:.2}/{:.2}/{:.2}/{:.2})",
                m.sum, m.body, m.object, m.rel, m.cg
            ),
            None => "-".to_string(),
        };
        println!(
            "{:<34} {:>4}-{:<4}  {:>5}  {:>30}  {:>30}  {:>30}",
            lib.clips[p.clip].name,
            p.window.start,
            p.window.release,
            p.replay.sm.map_or(0, |m| m.steps),
            cell(&p.replay),
            cell(&p.arms),
            cell(&p.upper),
        );
    }
    println!();
    println!(
        "push windows: the ball's horizontal speed at the release, m/s, and at the clip's next catch (a hand within hand_radius of its ball after its bounce) its distance from the clip's ball, both relative to the root, m (the clip's own targets after the release)"
    );
    println!(
        "{:<34} {:>9}  {:>5}  {:>5}  {:>13}  {:>13}  {:>13}",
        "clip", "frames", "catch", "clip", "own targets", "arms", "upper body"
    );
    for p in &fits {
        let Some(catch) = p.window.catch else {
            continue;
        };
        let cell =
            |s: &PushSearch| format!("{:5.2} ({:>5})", s.vel[0].hypot(s.vel[1]), opt(s.catch_err));
        println!(
            "{:<34} {:>4}-{:<4}  {:>5}  {:>5.2}  {:>13}  {:>13}  {:>13}",
            lib.clips[p.clip].name,
            p.window.start,
            p.window.release,
            catch,
            p.vel_ref[0].hypot(p.vel_ref[1]),
            cell(&p.replay),
            cell(&p.arms),
            cell(&p.upper),
        );
    }
    Ok(())
}
