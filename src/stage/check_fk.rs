//! `skillaug check-fk`: every frame of every selected clip is set into the
//! rapier3d world ([`crate::sim::World::set_state`]) and the body positions
//! read back ([`crate::sim::World::get_state`]) are compared with the
//! positions stored in the clip. Joints are exp-maps (docs/simulation.md).
//! Mean and max error per clip; ParaHome should agree to a few millimetres,
//! BallPlay and Locomotion to a few centimetres (the capture skeleton's limb
//! lengths differ from the model's).

use super::Common;
use crate::dataset;
use crate::ingest::{ingest_clip, IngestConfig};
use crate::sim::mjcf::Model;
use crate::sim::{SimOptions, World};
use anyhow::{Context, Result};
use rayon::prelude::*;

/// FK error of one clip, m.
#[derive(Clone, Debug)]
pub struct FkError {
    /// Clip name.
    pub name: String,
    /// Valid frames compared.
    pub frames: usize,
    /// Mean distance over bodies and frames.
    pub mean: f64,
    /// Largest distance.
    pub max: f64,
}

/// FK errors of every clip the arguments select.
pub fn errors(common: &Common) -> Result<Vec<FkError>> {
    let cfg: IngestConfig = common.settings("ingest")?;
    let set = common.clip_set(&cfg)?;
    let root = dataset::data_root(common.args.data_root.as_deref())?;
    let clips = set
        .clips
        .par_iter()
        .map(|src| ingest_clip(src, &set, &cfg).with_context(|| format!("{}", src.path.display())))
        .collect::<Result<Vec<_>>>()?;
    let mut models: Vec<(String, Model)> = Vec::new();
    for c in &clips {
        let sk = c.layout.skeleton();
        if !models.iter().any(|(n, _)| n == sk.name()) {
            models.push((sk.name().to_string(), Model::for_skeleton(&root, sk)?));
        }
    }
    clips
        .par_iter()
        .map(|c| {
            let sk = c.layout.skeleton();
            let m = &models.iter().find(|(n, _)| n == sk.name()).unwrap().1;
            // the humanoid alone: objects play no part in body positions
            let opts = SimOptions {
                angvel_frame: cfg.angvel_frame,
                ..SimOptions::for_fps(c.fps)
            };
            let mut world = World::new(m, &[], &opts)?;
            let f = &c.frames;
            let (mut sum, mut max, mut n, mut frames) = (0.0f64, 0.0f64, 0usize, 0usize);
            for i in 0..f.frames {
                let Some(mut s) = f.state(i) else { continue };
                s.obj_pos.clear();
                s.obj_rot.clear();
                s.obj_linvel.clear();
                s.obj_angvel.clear();
                world
                    .set_state(&s)
                    .with_context(|| format!("{} frame {i}", c.src.name))?;
                let p = world.get_state().body_pos;
                for (a, b) in p.chunks_exact(3).zip(s.body_pos.chunks_exact(3)) {
                    let d = ((a[0] - b[0]) as f64)
                        .hypot((a[1] - b[1]) as f64)
                        .hypot((a[2] - b[2]) as f64);
                    sum += d;
                    max = max.max(d);
                    n += 1;
                }
                frames += 1;
            }
            Ok(FkError {
                name: c.src.name.clone(),
                frames,
                mean: sum / n.max(1) as f64,
                max,
            })
        })
        .collect()
}

/// Run the command: print the table.
pub fn run(common: &Common) -> Result<()> {
    let errs = errors(common)?;
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
