//! `clips.parquet`: one row per ingested clip.

use super::columns::{specs, Column, TableRow};
use super::ColumnSpec;
use anyhow::Result;
use arrow::record_batch::RecordBatch;

/// One clip's row: the motion library's clip description
/// ([`crate::motion::library::ClipRow`]), one field per column.
pub use crate::motion::library::ClipRow;

impl TableRow for ClipRow {
    fn columns() -> Vec<Column<ClipRow>> {
        vec![
            Column::new("clip_id", "clip index within this table, 0-based, in manifest order (the key of frames.parquet)", |r: &ClipRow| r.clip_id),
            Column::new("name", "clip name (file stem)", |r: &ClipRow| r.name.clone()),
            Column::new("dataset", "dataset name (manifest name, or the --from folder's name)", |r: &ClipRow| r.dataset.clone()),
            Column::new("skill", "skill (the clip's folder name in the release)", |r: &ClipRow| r.skill.clone()),
            Column::new("class", "class id: the integer of the first three characters of the file name; condition slot of the one-hot skill vector (64 slots)", |r: &ClipRow| r.class as u32),
            Column::new("label", "human label (DF, DL, DR, Layup, Shot, Getup, Place-Book, ...)", |r: &ClipRow| r.label.clone()),
            Column::new("source", "source file, relative to the data root for manifest datasets", |r: &ClipRow| r.source.clone()),
            Column::new("sha256", "sha256 of the source file, hex", |r: &ClipRow| r.sha256.clone()),
            Column::new("frames", "frames in the clip, missing ones included", |r: &ClipRow| r.frames),
            Column::new("valid_frames", "frames that are not missing (all-zero rows are missing)", |r: &ClipRow| r.valid_frames),
            Column::new("fps", "frame rate, Hz (one frame per policy step)", |r: &ClipRow| r.fps),
            Column::new("duration_s", "frames / fps, s", |r: &ClipRow| r.frames as f32 / r.fps),
            Column::new("layout", "tensor layout: D337 (BallPlay, Locomotion), D409 or D415 (ParaHome, one or two objects)", |r: &ClipRow| r.layout.clone()),
            Column::new("skeleton", "humanoid model: mocap_humanoid (53 bodies) or mocap_parahome_boxhand (61 bodies)", |r: &ClipRow| r.skeleton.clone()),
            Column::new("objects", "names of the objects whose state is in frames.parquet, in order (empty for no-object clips)", |r: &ClipRow| r.objects.clone()),
        ]
    }
}

/// The documented columns.
pub fn columns() -> Vec<ColumnSpec> {
    specs::<ClipRow>()
}

/// The record batch of `rows`.
pub fn batch(rows: &[ClipRow]) -> Result<RecordBatch> {
    super::columns::batch(rows)
}

/// Read `clips.parquet` back.
pub fn read(path: &std::path::Path) -> Result<Vec<ClipRow>> {
    use super::read_util::{col, list_strs, strs};
    use arrow::array::AsArray;
    use arrow::datatypes::{Float32Type, UInt32Type};
    let t = super::io::read_parquet(path)?;
    super::read_util::check_table(&t, path, "clips")?;
    let mut rows = Vec::new();
    for b in &t.batches {
        let u32s = |n: &str| -> Result<Vec<u32>> {
            Ok(col(b, n, path)?
                .as_primitive::<UInt32Type>()
                .values()
                .to_vec())
        };
        let (ids, class, frames, valid) = (
            u32s("clip_id")?,
            u32s("class")?,
            u32s("frames")?,
            u32s("valid_frames")?,
        );
        let fps = col(b, "fps", path)?
            .as_primitive::<Float32Type>()
            .values()
            .to_vec();
        let (name, dataset, skill, label) = (
            strs(b, "name", path)?,
            strs(b, "dataset", path)?,
            strs(b, "skill", path)?,
            strs(b, "label", path)?,
        );
        let (source, sha, layout, skeleton) = (
            strs(b, "source", path)?,
            strs(b, "sha256", path)?,
            strs(b, "layout", path)?,
            strs(b, "skeleton", path)?,
        );
        let objects = list_strs(b, "objects", path)?;
        for i in 0..b.num_rows() {
            rows.push(ClipRow {
                clip_id: ids[i],
                name: name[i].clone(),
                dataset: dataset[i].clone(),
                skill: skill[i].clone(),
                class: u16::try_from(class[i]).unwrap_or(u16::MAX),
                label: label[i].clone(),
                source: source[i].clone(),
                sha256: sha[i].clone(),
                frames: frames[i],
                valid_frames: valid[i],
                fps: fps[i],
                layout: layout[i].clone(),
                skeleton: skeleton[i].clone(),
                objects: objects[i].clone(),
            });
        }
    }
    for (i, r) in rows.iter().enumerate() {
        if r.clip_id as usize != i {
            anyhow::bail!(
                "{}: clip_id {} at row {i}: clip ids must be 0, 1, 2, ...",
                path.display(),
                r.clip_id
            );
        }
    }
    Ok(rows)
}

/// The sum of the `frames` column of the clips table at `path` (every row
/// of every batch), without the checks [`super::load_library`] makes.
///
/// # Errors
/// When the file cannot be read as Parquet.
pub fn total_frames(path: &std::path::Path) -> Result<u64> {
    use arrow::array::AsArray;
    Ok(super::io::read_parquet(path)?
        .batches
        .iter()
        .map(|b| {
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
        .sum())
}
