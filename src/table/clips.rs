//! `clips.parquet`: one row per ingested clip.

use super::{schema_of, str_list, ColumnSpec};
use anyhow::Result;
use arrow::array::{ArrayRef, Float32Array, ListBuilder, StringArray, StringBuilder, UInt32Array};
use arrow::datatypes::{DataType, Field};
use arrow::record_batch::RecordBatch;
use std::sync::Arc;

/// The documented columns.
pub fn columns() -> Vec<ColumnSpec> {
    use DataType::*;
    vec![
        ColumnSpec::new("clip_id", UInt32, false, "clip index within this table, 0-based, in manifest order (the key of frames.parquet)"),
        ColumnSpec::new("name", Utf8, false, "clip name (file stem)"),
        ColumnSpec::new("dataset", Utf8, false, "dataset name (manifest name, or the --from folder's name)"),
        ColumnSpec::new("skill", Utf8, false, "skill (the clip's folder name in the release)"),
        ColumnSpec::new("class", UInt32, false, "class id: the integer of the first three characters of the file name; condition slot of the one-hot skill vector (64 slots)"),
        ColumnSpec::new("label", Utf8, false, "human label (DF, DL, DR, Layup, Shot, Getup, Place-Book, ...)"),
        ColumnSpec::new("source", Utf8, false, "source file, relative to the data root for manifest datasets"),
        ColumnSpec::new("sha256", Utf8, false, "sha256 of the source file, hex"),
        ColumnSpec::new("frames", UInt32, false, "frames in the clip, missing ones included"),
        ColumnSpec::new("valid_frames", UInt32, false, "frames that are not missing (all-zero rows are missing)"),
        ColumnSpec::new("fps", Float32, false, "frame rate, Hz (one frame per policy step)"),
        ColumnSpec::new("duration_s", Float32, false, "frames / fps, s"),
        ColumnSpec::new("layout", Utf8, false, "tensor layout: D337 (BallPlay, Locomotion), D409 or D415 (ParaHome, one or two objects)"),
        ColumnSpec::new("skeleton", Utf8, false, "humanoid model: mocap_humanoid (53 bodies) or mocap_parahome_boxhand (61 bodies)"),
        ColumnSpec::new("objects", str_list(), false, "names of the objects whose state is in frames.parquet, in order (empty for no-object clips)"),
    ]
}

/// One clip's row: the motion library's clip description
/// ([`crate::motion::library::ClipRow`]), one field per column.
pub use crate::motion::library::ClipRow;

/// The record batch of `rows`.
pub fn batch(rows: &[ClipRow]) -> Result<RecordBatch> {
    fn strs(rows: &[ClipRow], f: impl Fn(&ClipRow) -> &str) -> ArrayRef {
        Arc::new(StringArray::from_iter_values(rows.iter().map(f)))
    }
    let mut objects = ListBuilder::new(StringBuilder::new()).with_field(Arc::new(Field::new(
        "item",
        DataType::Utf8,
        false,
    )));
    for r in rows {
        for o in &r.objects {
            objects.values().append_value(o);
        }
        objects.append(true);
    }
    let arrays: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(
            rows.iter().map(|r| r.clip_id),
        )),
        strs(rows, |r| &r.name),
        strs(rows, |r| &r.dataset),
        strs(rows, |r| &r.skill),
        Arc::new(UInt32Array::from_iter_values(
            rows.iter().map(|r| r.class as u32),
        )),
        strs(rows, |r| &r.label),
        strs(rows, |r| &r.source),
        strs(rows, |r| &r.sha256),
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.frames))),
        Arc::new(UInt32Array::from_iter_values(
            rows.iter().map(|r| r.valid_frames),
        )),
        Arc::new(Float32Array::from_iter_values(rows.iter().map(|r| r.fps))),
        Arc::new(Float32Array::from_iter_values(
            rows.iter().map(|r| r.frames as f32 / r.fps),
        )),
        strs(rows, |r| &r.layout),
        strs(rows, |r| &r.skeleton),
        Arc::new(objects.finish()),
    ];
    Ok(RecordBatch::try_new(schema_of(&columns()), arrays)?)
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
