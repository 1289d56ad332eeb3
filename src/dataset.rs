//! Dataset manifests and the data root.
//!
//! Clips are never copied into the project: `datasets/<name>.toml` lists the
//! clips of a dataset (file, skill, class, label, sha256) relative to a data
//! root, which resolves as `--data-root` > `SKILLAUG_DATA` > the
//! `../shared/datasets` folder beside the checkout. A clip whose bytes do not
//! hash to the manifest's sha256 is refused.
//!
//! A plain folder of `.pt` files can be used instead (`--from DIR`): each
//! clip's skill is its parent folder's name and its class the integer formed by
//! the first three characters of its file name (as Ingrid789/SkillMimic-V2
//! `skillmimic/utils/motion_data_handler.py` derives it).

use crate::motion::Skeleton;
use anyhow::{anyhow, bail, Context, Result};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A dataset manifest, as stored in `datasets/<name>.toml`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Dataset-wide facts.
    pub dataset: DatasetInfo,
    /// The clips, in the order they get their clip ids.
    #[serde(rename = "clip")]
    pub clips: Vec<ClipEntry>,
    /// Named subsets: split name -> clip names (file stems).
    #[serde(default)]
    pub splits: BTreeMap<String, Vec<String>>,
}

/// The `[dataset]` table of a manifest.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetInfo {
    /// Dataset name.
    pub name: String,
    /// One paragraph for humans.
    pub description: String,
    /// Folder under the data root that holds the clips.
    pub folder: String,
    /// Frame rate of the clips, Hz.
    pub fps: f64,
    /// Skeleton name (`mocap_humanoid` or `mocap_parahome_boxhand`).
    pub skeleton: String,
    /// Objects in every clip (overridden per clip); `[]` drops the object columns.
    #[serde(default)]
    pub objects: Option<Vec<String>>,
    /// Where the data come from.
    pub source: String,
    /// Their licence.
    pub license: String,
}

/// One `[[clip]]` entry of a manifest.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClipEntry {
    /// Path relative to the dataset folder.
    pub file: String,
    /// Skill (the folder name in the releases).
    pub skill: String,
    /// Class id (first three characters of the file name).
    pub class: u16,
    /// Human label (e.g. DF, Layup, Place-Book).
    pub label: String,
    /// Expected sha256 of the file, hex.
    pub sha256: String,
    /// Objects of this clip, overriding the dataset's.
    #[serde(default)]
    pub objects: Option<Vec<String>>,
}

/// One clip to ingest.
#[derive(Debug, Clone)]
pub struct ClipSource {
    /// Clip name (file stem).
    pub name: String,
    /// Where to read it.
    pub path: PathBuf,
    /// The path recorded in the tables (relative to the data root for manifests).
    pub source: String,
    /// Skill.
    pub skill: String,
    /// Class id.
    pub class: u16,
    /// Label.
    pub label: String,
    /// Expected hash, when a manifest gives one.
    pub sha256: Option<String>,
    /// Object names, when known; `None` = one per object the layout stores.
    pub objects: Option<Vec<String>>,
}

/// The clips of one ingest run.
#[derive(Debug, Clone)]
pub struct ClipSet {
    /// Dataset name recorded in the tables.
    pub dataset: String,
    /// Frame rate, when the manifest gives one.
    pub fps: Option<f64>,
    /// Skeleton, when the manifest gives one.
    pub skeleton: Option<Skeleton>,
    /// Clips in clip-id order.
    pub clips: Vec<ClipSource>,
}

/// Folders where `datasets/` manifests are looked up: the working directory,
/// then the checkout this binary was built from.
fn project_dirs() -> Vec<PathBuf> {
    let mut v = vec![PathBuf::from(".")];
    let built = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    if built.exists() {
        v.push(built);
    }
    v
}

/// Resolve the data root: `--data-root` or `SKILLAUG_DATA` (merged by the CLI
/// parser, flag first), else `../shared/datasets` beside the checkout.
pub fn data_root(given: Option<&Path>) -> Result<PathBuf> {
    if let Some(p) = given {
        if !p.is_dir() {
            bail!(
                "data root {} does not exist (from --data-root or SKILLAUG_DATA); \
                 it must hold the BallPlay-M / Locomotion / ParaHome releases as \
                 ballplay/, ballplay-m/, locomotion/, parahome/",
                p.display()
            );
        }
        return Ok(p.to_path_buf());
    }
    for dir in project_dirs() {
        let cand = dir.join("../shared/datasets");
        if cand.is_dir() {
            return Ok(cand);
        }
    }
    bail!(
        "no data root found: put the BallPlay-M / Locomotion / ParaHome releases \
         (folders ballplay/, ballplay-m/, locomotion/, parahome/ of .pt clips) in \
         ../shared/datasets beside the checkout, or point --data-root or \
         SKILLAUG_DATA at them"
    )
}

/// Find the manifest of `name`: a path to a `.toml` file, or a name looked up
/// as `datasets/<name>.toml`.
pub fn find_manifest(name: &str) -> Result<PathBuf> {
    if name.ends_with(".toml") || name.contains('/') {
        let p = PathBuf::from(name);
        if !p.is_file() {
            bail!("manifest {} does not exist", p.display());
        }
        return Ok(p);
    }
    let dirs = project_dirs();
    for dir in &dirs {
        let p = dir.join("datasets").join(format!("{name}.toml"));
        if p.is_file() {
            return Ok(p);
        }
    }
    let mut known: Vec<String> = dirs
        .iter()
        .filter_map(|d| std::fs::read_dir(d.join("datasets")).ok())
        .flatten()
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let n = e.file_name().to_string_lossy().to_string();
            n.strip_suffix(".toml").map(str::to_string)
        })
        .collect();
    known.sort();
    known.dedup();
    bail!(
        "unknown dataset `{name}` (known: {}); pass a name from datasets/ or a manifest path",
        if known.is_empty() {
            "none found".to_string()
        } else {
            known.join(", ")
        }
    )
}

/// Read and check a manifest.
pub fn load_manifest(path: &Path) -> Result<Manifest> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read manifest {}", path.display()))?;
    let m: Manifest = toml::from_str(&text)
        .map_err(|e| anyhow!("manifest {}: {}", path.display(), e.message()))?;
    if Skeleton::from_name(&m.dataset.skeleton).is_none() {
        bail!(
            "manifest {}: unknown skeleton `{}` (known: mocap_humanoid, mocap_parahome_boxhand)",
            path.display(),
            m.dataset.skeleton
        );
    }
    if !m.dataset.fps.is_finite() || m.dataset.fps <= 0.0 {
        bail!("manifest {}: fps must be positive", path.display());
    }
    for (split, names) in &m.splits {
        for n in names {
            if !m.clips.iter().any(|c| stem(&c.file) == *n) {
                bail!(
                    "manifest {}: split `{split}` names clip `{n}`, which the manifest does not list",
                    path.display()
                );
            }
        }
    }
    Ok(m)
}

fn stem(file: &str) -> String {
    Path::new(file)
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_default()
}

/// The clips a manifest selects: all, or one split, optionally only some skills.
pub fn from_manifest(
    manifest_path: &Path,
    root: &Path,
    split: &str,
    skills: &[String],
) -> Result<ClipSet> {
    let m = load_manifest(manifest_path)?;
    let chosen: Option<&Vec<String>> = if split.is_empty() {
        None
    } else {
        Some(m.splits.get(split).ok_or_else(|| {
            anyhow!(
                "manifest {}: unknown split `{split}` (known: {})",
                manifest_path.display(),
                if m.splits.is_empty() {
                    "none".to_string()
                } else {
                    m.splits.keys().cloned().collect::<Vec<_>>().join(", ")
                }
            )
        })?)
    };
    for s in skills {
        if !m.clips.iter().any(|c| &c.skill == s) {
            bail!(
                "manifest {}: no clip has skill `{s}`",
                manifest_path.display()
            );
        }
    }
    let folder = root.join(&m.dataset.folder);
    if !folder.is_dir() {
        bail!(
            "dataset folder {} does not exist: put the {} release there, or point \
             --data-root / SKILLAUG_DATA at a folder holding `{}/`",
            folder.display(),
            m.dataset.name,
            m.dataset.folder
        );
    }
    let clips = m
        .clips
        .iter()
        .filter(|c| chosen.is_none_or(|names| names.contains(&stem(&c.file))))
        .filter(|c| skills.is_empty() || skills.contains(&c.skill))
        .map(|c| ClipSource {
            name: stem(&c.file),
            path: folder.join(&c.file),
            source: format!("{}/{}", m.dataset.folder, c.file),
            skill: c.skill.clone(),
            class: c.class,
            label: c.label.clone(),
            sha256: Some(c.sha256.to_ascii_lowercase()),
            objects: c.objects.clone().or_else(|| m.dataset.objects.clone()),
        })
        .collect();
    Ok(ClipSet {
        dataset: m.dataset.name.clone(),
        fps: Some(m.dataset.fps),
        skeleton: Skeleton::from_name(&m.dataset.skeleton),
        clips,
    })
}

/// Every `.pt` file under `dir` (recursively, sorted by path), with skill =
/// parent folder name and class = first three characters of the file name.
pub fn from_folder(dir: &Path) -> Result<ClipSet> {
    if !dir.is_dir() {
        bail!("--from {}: not a folder", dir.display());
    }
    let mut files = Vec::new();
    collect_pt(dir, &mut files)?;
    files.sort();
    if files.is_empty() {
        bail!("--from {}: no .pt files found", dir.display());
    }
    let dataset = dir
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().to_string()))
        .unwrap_or_else(|| "folder".into());
    let mut clips = Vec::new();
    for path in files {
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_default();
        let skill = path
            .parent()
            .and_then(|p| p.file_name())
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_default();
        let class = class_of(&name).ok_or_else(|| {
            anyhow!(
                "{}: the first three characters of the file name must be the class number (e.g. 013_run.pt)",
                path.display()
            )
        })?;
        clips.push(ClipSource {
            source: path.display().to_string(),
            label: skill.clone(),
            name,
            path,
            skill,
            class,
            sha256: None,
            objects: None,
        });
    }
    Ok(ClipSet {
        dataset,
        fps: None,
        skeleton: None,
        clips,
    })
}

/// The class number of a clip name: the integer of its first three characters.
pub fn class_of(name: &str) -> Option<u16> {
    name.get(..3)?.parse().ok()
}

fn collect_pt(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let entries =
        std::fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))?;
    for e in entries {
        let path = e?.path();
        if path.is_dir() {
            collect_pt(&path, out)?;
        } else if path.extension().is_some_and(|x| x == "pt") {
            out.push(path);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn class_is_the_first_three_characters() {
        assert_eq!(class_of("031_015pickle_layup_001_006"), Some(31));
        assert_eq!(class_of("023pickle_layup_7"), Some(23));
        assert_eq!(class_of("ab1_x"), None);
        assert_eq!(class_of("01"), None);
    }

    #[test]
    fn shipped_manifests_parse_and_their_splits_nest() {
        for name in ["ballplay", "ballplay-m", "locomotion", "parahome"] {
            let m = load_manifest(&find_manifest(name).unwrap()).unwrap();
            assert_eq!(m.dataset.name, name);
            assert!(!m.clips.is_empty());
        }
        let m = load_manifest(&find_manifest("ballplay-m").unwrap()).unwrap();
        let sizes: Vec<usize> = ["pickup-1", "pickup-4", "pickup-10", "pickup-40"]
            .iter()
            .map(|s| m.splits[*s].len())
            .collect();
        assert_eq!(sizes, [1, 4, 10, 39]);
        for w in ["pickup-1", "pickup-4", "pickup-10", "pickup-40"].windows(2) {
            assert!(m.splits[w[0]].iter().all(|c| m.splits[w[1]].contains(c)));
        }
        let b = load_manifest(&find_manifest("ballplay").unwrap()).unwrap();
        let mut labels: Vec<&str> = b.clips.iter().map(|c| c.label.as_str()).collect();
        labels.dedup();
        assert_eq!(labels, ["Layup", "DL", "DR", "DF", "Shot"]);
    }
}
