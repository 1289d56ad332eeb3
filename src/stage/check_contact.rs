//! `skillaug check-contact`: what the clips' contact flag measures. Every
//! valid frame of every clip with a ball (an ingested run folder, `--from`)
//! is set into the rapier3d world ([`crate::sim::checks::contact_agreements`])
//! and three rules are compared with the flag frame by frame: hand-ball
//! proximity at `train.contact_radius` (the trainer's default rule),
//! touching pairs at any physics substep of one policy step from the frame,
//! and touching pairs after the last substep only. It also prints the
//! radius, from 0.10 m to 0.40 m, at which the proximity rule agrees best.

use super::Common;
use crate::sim::checks::{contact_agreements, ContactAgreement};
use crate::sim::mjcf::Model;
use anyhow::{bail, Result};

/// Run the command: print the table.
pub fn run(common: &Common) -> Result<()> {
    let cfg: crate::rl::config::TrainConfig = common.settings("train")?;
    let lib = crate::table::load_library(common.input_dir())?;
    let root = crate::dataset::data_root(common.args.data_root.as_deref())?;
    let model = Model::for_skeleton(&root, lib.skeleton)?;
    let radius = cfg.contact_radius as f32;
    let found = contact_agreements(&lib, &model, &root)?;
    if found.is_empty() {
        bail!(
            "check-contact: no clip in {} has an object",
            common.input_dir().display()
        );
    }
    println!(
        "{:<34} {:>6} {:>6} {:>10} {:>9} {:>10}",
        "clip",
        "frames",
        "flag",
        format!("prox {:.2}", radius),
        "touch",
        "touch-last"
    );
    for (c, a) in &found {
        println!(
            "{:<34} {:>6} {:>5.0}% {:>9.1}% {:>8.1}% {:>9.1}%",
            lib.clips[*c].name,
            a.frames,
            100.0 * a.flagged as f64 / a.frames.max(1) as f64,
            100.0 * a.proximity(radius),
            100.0 * a.agreement(|r| r.touch_any),
            100.0 * a.agreement(|r| r.touch_last),
        );
    }
    let total = ContactAgreement::all(found.iter().map(|(_, a)| a));
    let n = total.frames;
    println!(
        "all {} frames: flag set in {:.1}%; agreement: proximity {:.2} m {:.1}%, touch (any substep) {:.1}%, touch (last substep) {:.1}%",
        n,
        100.0 * total.flagged as f64 / n.max(1) as f64,
        radius,
        100.0 * total.proximity(radius),
        100.0 * total.agreement(|r| r.touch_any),
        100.0 * total.agreement(|r| r.touch_last),
    );
    let (best_r, best) = total.best_radius();
    println!(
        "best proximity radius {best_r:.2} m: {:.1}% agreement",
        100.0 * best
    );
    Ok(())
}
