//! `skillaug ingest`: motion clips (`.pt`) into `clips.parquet` and
//! `frames.parquet` (the clip format of Ingrid789/SkillMimic-V2, read there by
//! `skillmimic/utils/motion_data_handler.py`; derivations in
//! [`crate::motion::clip`]).

use super::{Common, Outputs};
use crate::dataset::{self, ClipSet, ClipSource};
use crate::motion::clip::{self, AngvelFrame, ObjAngvel};
use crate::motion::{ClipFrames, DeriveOptions, Layout, Skeleton};
use crate::table::{self, clips::ClipRow, frames::ClipInput};
use crate::{progress, pt};
use anyhow::{anyhow, bail, Context, Result};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::time::Instant;

/// Settings of the `[ingest]` recipe table.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IngestConfig {
    /// Named split of the manifest to ingest ("" = every clip), e.g. `pickup-4`.
    pub split: String,
    /// Only these skills (empty = all).
    pub skills: Vec<String>,
    /// Frame rate for finite differences, Hz; 0 = the manifest's, else 60 for
    /// D = 337 and 30 for ParaHome layouts (the `dataFPS` of
    /// Ingrid789/SkillMimic-V2 `skillmimic/data/cfg/skillmimic.yaml` and
    /// `skillmimic_parahome.yaml`).
    pub fps: f64,
    /// Frame of the root and object angular velocities: "body" (the reference
    /// loader, Ingrid789/SkillMimic-V2 `skillmimic/utils/motion_data_handler.py`)
    /// or "world".
    pub angvel_frame: AngvelFrame,
    /// Object angular velocity: "quat-diff" (true angular velocity) or
    /// "expmap-diff" (the reference code's difference of rotation vectors).
    pub obj_angvel: ObjAngvel,
    /// Ingest the good clips and list the bad ones instead of failing.
    pub skip_bad: bool,
}

impl crate::config::Validate for IngestConfig {
    fn validate(&self, stage: &str) -> Result<()> {
        let c = crate::config::Check::new(stage);
        c.holds(
            self.fps == 0.0 || (self.fps.is_finite() && (1.0..=10_000.0).contains(&self.fps)),
            || {
                format!(
                    "fps = {}: must be 0 (the manifest's rate) or a frame rate in [1, 10000] Hz",
                    self.fps
                )
            },
        )
    }
}

impl Default for IngestConfig {
    fn default() -> Self {
        IngestConfig {
            split: String::new(),
            skills: Vec::new(),
            fps: 0.0,
            angvel_frame: AngvelFrame::Body,
            obj_angvel: ObjAngvel::QuatDiff,
            skip_bad: false,
        }
    }
}

/// One clip read and derived.
pub(crate) struct Ingested {
    pub(crate) src: ClipSource,
    pub(crate) sha256: String,
    pub(crate) layout: Layout,
    pub(crate) fps: f64,
    pub(crate) objects: Vec<String>,
    pub(crate) frames: ClipFrames,
}

/// Read, check and derive one clip.
pub(crate) fn ingest_clip(src: &ClipSource, set: &ClipSet, cfg: &IngestConfig) -> Result<Ingested> {
    let bytes = std::fs::read(&src.path).context("cannot read the file")?;
    let sha256 = hex::encode(Sha256::digest(&bytes));
    if let Some(want) = &src.sha256 {
        if *want != sha256 {
            bail!("sha256 {sha256} differs from the manifest's {want}: the file has changed");
        }
    }
    let m = pt::read_f32_matrix(&bytes)?;
    let layout = Layout::from_columns(m.cols).ok_or_else(|| {
        anyhow!(
            "tensor of shape [{}, {}]: {} columns is not a known layout (337 BallPlay/Locomotion, 409 or 415 ParaHome)",
            m.rows,
            m.cols,
            m.cols
        )
    })?;
    if let Some(sk) = set.skeleton {
        if sk != layout.skeleton() {
            bail!(
                "{} columns ({layout}) belong to skeleton {}, but the manifest says {sk}",
                m.cols,
                layout.skeleton()
            );
        }
    }
    let fps = if cfg.fps > 0.0 {
        cfg.fps
    } else {
        set.fps.unwrap_or(layout.default_fps())
    };
    let stored = layout.objects().len();
    let objects = match &src.objects {
        Some(o) if o.len() > stored => bail!(
            "the manifest names {} objects ({}) but layout {layout} stores {stored}",
            o.len(),
            o.join(", ")
        ),
        Some(o) => o.clone(),
        None if layout == Layout::BallPlay337 => vec!["ball".to_string()],
        None => (0..stored).map(|i| format!("object{i}")).collect(),
    };
    let opts = DeriveOptions {
        fps,
        angvel_frame: cfg.angvel_frame,
        obj_angvel: cfg.obj_angvel,
        n_objects: objects.len(),
    };
    let frames = clip::derive(&m.data, layout, &opts)?;
    if let Some(why) = crate::motion::library::unusable(&frames) {
        bail!("{why}");
    }
    Ok(Ingested {
        src: src.clone(),
        sha256,
        layout,
        fps,
        objects,
        frames,
    })
}

/// The clips a run selects: a manifest (`--dataset`) or a folder (`--from`).
pub(crate) fn clip_set(common: &Common, cfg: &IngestConfig) -> Result<ClipSet> {
    let set = match (&common.args.dataset, &common.args.from) {
        (Some(name), None) => {
            let manifest = dataset::find_manifest(name)?;
            let root = dataset::data_root(common.args.data_root.as_deref())?;
            dataset::from_manifest(&manifest, &root, &cfg.split, &cfg.skills)?
        }
        (None, Some(dir)) => {
            if !cfg.split.is_empty() {
                bail!("ingest.split = `{}` needs a manifest (--dataset); --from folders have no splits", cfg.split);
            }
            let mut s = dataset::from_folder(dir)?;
            if !cfg.skills.is_empty() {
                s.clips.retain(|c| cfg.skills.contains(&c.skill));
            }
            s
        }
        _ => bail!("this command needs --dataset NAME or --from DIR"),
    };
    if set.clips.is_empty() {
        bail!("no clips selected");
    }
    crate::motion::library::check_classes(
        set.clips
            .iter()
            .map(|c| (c.name.as_str(), c.skill.as_str(), c.class as u32)),
    )?;

    Ok(set)
}

/// Run the stage.
pub fn run(common: &Common, skip_bad_flag: bool) -> Result<()> {
    let started = Instant::now();
    let mut cfg: IngestConfig = common.settings("ingest")?;
    cfg.skip_bad |= skip_bad_flag;
    let _lock = common.lock_output("ingest")?;
    let set = clip_set(common, &cfg)?;

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

    let rows: Vec<ClipRow> = good
        .iter()
        .enumerate()
        .map(|(i, c)| ClipRow {
            clip_id: i as u32,
            name: c.src.name.clone(),
            dataset: set.dataset.clone(),
            skill: c.src.skill.clone(),
            class: c.src.class,
            label: c.src.label.clone(),
            source: c.src.source.clone(),
            sha256: c.sha256.clone(),
            frames: c.frames.frames as u32,
            valid_frames: c.frames.valid_frames() as u32,
            fps: c.fps as f32,
            layout: c.layout.name().to_string(),
            skeleton: skeleton.name().to_string(),
            objects: c.objects.clone(),
        })
        .collect();
    let inputs: Vec<ClipInput> = good
        .iter()
        .enumerate()
        .map(|(i, c)| ClipInput {
            clip_id: i as u32,
            fps: c.fps,
            frames: &c.frames,
        })
        .collect();

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

/// Key-value metadata common to both tables.
fn metadata(
    dataset: &str,
    skeleton: Skeleton,
    clips: &[Ingested],
    cfg: &IngestConfig,
    resolved: &str,
) -> Result<table::Meta> {
    let fps: Vec<f64> = clips.iter().map(|c| c.fps).collect();
    let fps_text = if fps.iter().all(|f| *f == fps[0]) {
        format!("{}", fps[0])
    } else {
        "mixed: see clips.parquet".into()
    };
    let hashes: BTreeMap<&str, &str> = clips
        .iter()
        .map(|c| (c.src.source.as_str(), c.sha256.as_str()))
        .collect();
    let name = |v: serde_json::Value| v.as_str().unwrap_or_default().to_string();
    Ok(table::Meta::new(dataset, resolved)
        .with("skeleton", skeleton.name())
        .with("n_joints", skeleton.n_joints().to_string())
        .with("n_bodies", skeleton.n_bodies().to_string())
        .with("body_names", serde_json::to_string(skeleton.body_names())?)
        .with("quaternion_order", "xyzw")
        .with("fps", fps_text)
        .with(
            "angvel_frame",
            name(serde_json::to_value(cfg.angvel_frame)?),
        )
        .with("obj_angvel", name(serde_json::to_value(cfg.obj_angvel)?))
        .with("source_sha256", serde_json::to_string(&hashes)?))
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
