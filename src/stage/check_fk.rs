//! `skillaug check-fk`: every frame of every selected clip is set into the
//! rapier3d world and the body positions read back are compared with the
//! positions stored in the clip ([`crate::sim::checks::fk_errors`]). Joints
//! are exp-maps (docs/simulation.md). Mean and max error per clip; ParaHome should agree to a few millimetres,
//! BallPlay and Locomotion to a few centimetres (the capture skeleton's limb
//! lengths differ from the model's).

use super::Common;
use crate::dataset;
use crate::ingest::{ingest_clip, IngestConfig};
use crate::sim::checks::fk_errors;
use anyhow::{Context, Result};
use rayon::prelude::*;

/// Run the command: print the table.
pub fn run(common: &Common) -> Result<()> {
    let cfg: IngestConfig = common.settings("ingest")?;
    let set = common.clip_set(&cfg)?;
    let root = dataset::data_root(common.args.data_root.as_deref())?;
    let clips = set
        .clips
        .par_iter()
        .map(|src| ingest_clip(src, &set, &cfg).with_context(|| format!("{}", src.path.display())))
        .collect::<Result<Vec<_>>>()?;
    let errs = fk_errors(&clips, &root, cfg.angvel_frame)?;
    println!(
        "{:<40} {:>6} {:>9} {:>9}",
        "clip", "frames", "mean cm", "max cm"
    );
    for e in &errs {
        println!(
            "{:<40} {:>6} {:>9.2} {:>9.2}",
            e.name,
            e.frames,
            100.0 * e.mean,
            100.0 * e.max
        );
    }
    let worst = errs.iter().map(|e| e.mean).fold(0.0, f64::max);
    println!(
        "{} clips; worst clip mean error {:.2} cm",
        errs.len(),
        100.0 * worst
    );
    Ok(())
}
