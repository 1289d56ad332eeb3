//! `skillaug bench NAME`: benchmarks that print figures (never timed tests).
//!
//! `bench ingest` ingests every shipped dataset (all four manifests, every
//! clip in the data root) into a temporary folder, `--repeat` times, and prints
//! the median wall time per dataset and in total, with the throughput.

use crate::cli::StageArgs;
use anyhow::{bail, Result};
use std::path::PathBuf;
use std::time::Instant;

/// Datasets `bench ingest` covers.
const DATASETS: [&str; 4] = ["ballplay", "ballplay-m", "locomotion", "parahome"];

/// Run benchmark `what`.
pub fn run(what: &str, repeat: usize, data_root: Option<PathBuf>) -> Result<()> {
    match what {
        "ingest" => ingest(repeat.max(1), data_root),
        other => bail!("unknown benchmark `{other}` (known: ingest)"),
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
            let args = StageArgs {
                out: out.clone(),
                dataset: Some(name.to_string()),
                from: None,
                data_root: data_root.clone(),
                recipe: None,
                set: Vec::new(),
                seed: 0,
                threads: None,
                quiet: true,
            };
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
