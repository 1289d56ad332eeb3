//! Motion clips (`.pt`) into the rows of `clips.parquet` and
//! `frames.parquet` (the clip format of Ingrid789/SkillMimic-V2, read there
//! by `skillmimic/utils/motion_data_handler.py`; derivations in
//! [`crate::motion::clip`]): the `[ingest]` settings, the clip selection,
//! reading and deriving one clip, the table rows and their metadata.

use crate::dataset::{self, ClipSet, ClipSource};
use crate::motion::clip::{self, AngvelFrame, ObjAngvel};
use crate::motion::{ClipFrames, DeriveOptions, Layout, Skeleton};
use crate::pt;
use crate::table::{self, clips::ClipRow, frames::ClipInput};
use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::path::Path;

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
pub struct Ingested {
    /// Where it came from.
    pub src: ClipSource,
    /// SHA-256 of the file.
    pub sha256: String,
    /// The column layout.
    pub layout: Layout,
    /// Frame rate used for the derivatives, Hz.
    pub fps: f64,
    /// Object names.
    pub objects: Vec<String>,
    /// The derived frames.
    pub frames: ClipFrames,
}

/// Read, check and derive one clip.
///
/// # Errors
/// An unreadable file, a hash that differs from the manifest's, a tensor
/// of an unknown layout or skeleton, too many objects, or a clip without
/// two consecutive valid frames.
pub fn ingest_clip(src: &ClipSource, set: &ClipSet, cfg: &IngestConfig) -> Result<Ingested> {
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

/// The clips a run selects: a manifest (`dataset`, `--dataset`) or a folder
/// (`from`, `--from`), with the data root `data_root` (`--data-root`).
///
/// # Errors
/// Neither or both of `dataset` and `from`, an unknown manifest, a split
/// with a folder, no clip selected, or class ids that do not fit
/// ([`crate::motion::library::check_classes`]).
pub fn clip_set(
    dataset: Option<&str>,
    from: Option<&Path>,
    data_root: Option<&Path>,
    cfg: &IngestConfig,
) -> Result<ClipSet> {
    let set = match (dataset, from) {
        (Some(name), None) => {
            let manifest = dataset::find_manifest(name)?;
            let root = dataset::data_root(data_root)?;
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

/// The rows of `clips.parquet` and the clips of `frames.parquet` for the
/// ingested clips `good` of `dataset`, numbered in order.
pub fn table_rows<'a>(
    good: &'a [Ingested],
    dataset: &str,
    skeleton: Skeleton,
) -> (Vec<ClipRow>, Vec<ClipInput<'a>>) {
    let rows: Vec<ClipRow> = good
        .iter()
        .enumerate()
        .map(|(i, c)| ClipRow {
            clip_id: i as u32,
            name: c.src.name.clone(),
            dataset: dataset.to_string(),
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
    (rows, inputs)
}

/// Key-value metadata common to both tables.
///
/// # Errors
/// Settings that cannot be written as JSON.
pub fn metadata(
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
