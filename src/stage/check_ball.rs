//! `skillaug check-ball`: can the clips' own motion keep their ball? Every
//! clip with a ball (an ingested run folder, `--from`) is replayed with the
//! humanoid set to each frame in turn while the ball is simulated from the
//! first RSI start frame on ([`crate::sim::checks::ball_replays`]), once with the
//! humanoid's bodies dynamic (the ball pushes back on the hands, as in
//! training) and once kinematic (an infinitely strong body). It prints how
//! far the simulated ball ends from the clip's and how hard it hits the
//! floor at its first bounce and how high it rises after it, beside the
//! clip's own figures.

use super::Common;
use crate::sim::checks::ball_replays;
use crate::sim::mjcf::Model;
use anyhow::{bail, Result};

fn opt(x: Option<f64>) -> String {
    x.map_or_else(|| "-".to_string(), |v| format!("{v:.2}"))
}

/// Run the command: print the table.
pub fn run(common: &Common) -> Result<()> {
    let lib = crate::table::load_library(common.input_dir())?;
    let root = crate::dataset::data_root(common.args.data_root.as_deref())?;
    let model = Model::for_skeleton(&root, lib.skeleton)?;
    let found = ball_replays(&lib, &model, &root)?;
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
    Ok(())
}
