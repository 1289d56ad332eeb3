//! `skillaug ingest`: motion clips (`.pt`) into `clips.parquet` and
//! `frames.parquet` ([`crate::ingest`]), in parallel, all or nothing (or the
//! good clips with `--skip-bad`), with a summary per skill.

use super::Common;
use crate::dataset::ClipSource;
use crate::ingest::{ingest_clip, metadata, table_rows, IngestConfig, Ingested};
use crate::table::io::Outputs;
use crate::{progress, table};
use anyhow::{bail, Result};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::time::Instant;

/// Run the stage.
pub fn run(common: &Common, skip_bad_flag: bool) -> Result<()> {
    let started = Instant::now();
    let mut cfg: IngestConfig = common.settings("ingest")?;
    cfg.skip_bad |= skip_bad_flag;
    let _lock = common.lock_output("ingest")?;
    let set = common.clip_set(&cfg)?;

    let bar = progress::bar(set.clips.len() as u64, "ingest", common.args.quiet);
    let results: Vec<(ClipSource, Result<Ingested>)> = set
        .clips
        .par_iter()
        .map(|src| {
            let r = ingest_clip(src, &set, &cfg);
            bar.inc(1);
            (src.clone(), r)
        })
        .collect();
    bar.finish_and_clear();

    let mut good = Vec::new();
    let mut bad = Vec::new();
    for (src, r) in results {
        match r {
            Ok(c) => good.push(c),
            Err(e) => bad.push(format!("{}: {e:#}", src.path.display())),
        }
    }
    if !bad.is_empty() && !cfg.skip_bad {
        bail!(
            "{} of {} clips could not be ingested (nothing was written; --skip-bad ingests the rest):\n  {}",
            bad.len(),
            set.clips.len(),
            bad.join("\n  ")
        );
    }
    if good.is_empty() {
        bail!("every clip was bad:\n  {}", bad.join("\n  "));
    }
    let skeleton = good[0].layout.skeleton();
    if let Some(other) = good.iter().find(|c| c.layout.skeleton() != skeleton) {
        bail!(
            "clips of two skeletons in one run: {} is {} but {} is {}; ingest them into separate folders",
            good[0].src.path.display(),
            skeleton,
            other.src.path.display(),
            other.layout.skeleton()
        );
    }

    let (rows, inputs) = table_rows(&good, &set.dataset, skeleton);

    let resolved = common.resolved_toml("ingest", &cfg)?;
    let meta = metadata(&set.dataset, skeleton, &good, &cfg, &resolved)?;
    let mut out = Outputs::new(&common.args.out)?;
    let clips_meta = meta.table("clips");
    let frames_meta = meta.table("frames");
    out.parquet("clips.parquet", &table::clips::batch(&rows)?, &clips_meta)?;
    out.parquet(
        "frames.parquet",
        &table::frames::batch(&inputs)?,
        &frames_meta,
    )?;
    out.text("ingest.resolved.toml", &resolved)?;
    out.commit()?;

    if !bad.is_empty() {
        eprintln!("skipped {} bad clip(s):\n  {}", bad.len(), bad.join("\n  "));
        let mut lost: Vec<&str> = set
            .clips
            .iter()
            .map(|c| c.skill.as_str())
            .filter(|s| !good.iter().any(|g| g.src.skill == *s))
            .collect();
        lost.sort_unstable();
        lost.dedup();
        if !lost.is_empty() {
            eprintln!(
                "warning: skill(s) left with no clip, not in the tables: {}",
                lost.join(", ")
            );
        }
    }
    if !common.args.quiet {
        print_summary(&good, &common.args.out, started.elapsed().as_secs_f64());
    }
    Ok(())
}

fn print_summary(clips: &[Ingested], out: &std::path::Path, secs: f64) {
    let mut per: BTreeMap<&str, (usize, usize, f64)> = BTreeMap::new();
    for c in clips {
        let e = per.entry(c.src.skill.as_str()).or_default();
        e.0 += 1;
        e.1 += c.frames.frames;
        e.2 += c.frames.frames as f64 / c.fps;
    }
    println!(
        "{:<16} {:>5} {:>7} {:>8}",
        "skill", "clips", "frames", "secs"
    );
    for (skill, (n, f, s)) in &per {
        println!("{skill:<16} {n:>5} {f:>7} {s:>8.2}");
    }
    let frames: usize = clips.iter().map(|c| c.frames.frames).sum();
    let valid: usize = clips.iter().map(|c| c.frames.valid_frames()).sum();
    println!(
        "ingested {} clips, {frames} frames ({valid} valid) into {} in {secs:.2} s",
        clips.len(),
        out.display()
    );
}
