//! `stg_edges.parquet` and `stg_summary.parquet`: the Stitched Trajectory
//! Graph (paper Section 4.4, Appendix B.4; reference code:
//! Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/offline_state_search.py`).

use super::read_util::{check_table, col, strs};
use super::{schema_of, ColumnSpec};
use crate::augment::stg::{Edge, SkillSummary};
use anyhow::{bail, Result};
use arrow::array::{
    ArrayRef, AsArray, Float32Array, Float64Array, ListBuilder, StringArray, UInt32Array,
    UInt32Builder,
};
use arrow::datatypes::{DataType, Field, Float32Type, Float64Type, UInt32Type};
use arrow::record_batch::RecordBatch;
use std::path::Path;
use std::sync::Arc;

/// Columns of `stg_edges.parquet`: one kept connection each.
pub fn columns() -> Vec<ColumnSpec> {
    use DataType::*;
    vec![
        ColumnSpec::new(
            "target_skill",
            Utf8,
            false,
            "skill A whose graph the edge belongs to (the skill to be tracked after the switch)",
        ),
        ColumnSpec::new(
            "target_class",
            UInt32,
            false,
            "class id of A (the condition during the stitched trajectory)",
        ),
        ColumnSpec::new(
            "src_skill",
            Utf8,
            false,
            "skill of the external start state",
        ),
        ColumnSpec::new(
            "src_clip",
            UInt32,
            false,
            "clip of the external start state (clips.parquet clip_id)",
        ),
        ColumnSpec::new(
            "src_frame",
            UInt32,
            false,
            "frame of the external start state",
        ),
        ColumnSpec::new("dst_clip", UInt32, false, "clip of A the start connects to"),
        ColumnSpec::new(
            "dst_frame",
            UInt32,
            false,
            "frame of A the start connects to (argmax of S_k)",
        ),
        ColumnSpec::new(
            "beta",
            Float64,
            false,
            "similarity S_k (Eq. 19) of the aligned start and the target frame, > tau",
        ),
        ColumnSpec::new(
            "n_masked",
            UInt32,
            false,
            "masked states between start and target (Eq. 20)",
        ),
        ColumnSpec::new(
            "align_yaw",
            Float32,
            false,
            "turn about the vertical through the start's root applied to the start state, rad",
        ),
        ColumnSpec::new(
            "align_dx",
            Float32,
            false,
            "then this x shift, m (start root x -> target root x)",
        ),
        ColumnSpec::new("align_dy", Float32, false, "then this y shift, m"),
    ]
}

/// Columns of `stg_summary.parquet`: one row per target skill.
pub fn summary_columns() -> Vec<ColumnSpec> {
    use DataType::*;
    vec![
        ColumnSpec::new("target_skill", Utf8, false, "skill A"),
        ColumnSpec::new("states", UInt32, false, "external states considered (valid frames of the other skills' clips; per-target mode: frames of A x other skills)"),
        ColumnSpec::new("kept", UInt32, false, "edges with beta > tau"),
        ColumnSpec::new("dropped", UInt32, false, "states without a connection (beta <= tau)"),
        ColumnSpec::new("n_hist", super::u32_list(), false, "kept edges per masked-state count N = 0, 1, ..., N_max"),
        ColumnSpec::new("beta_median", Float64, true, "median beta of the kept edges"),
    ]
}

/// The record batch of `edges`.
pub fn batch(edges: &[Edge]) -> Result<RecordBatch> {
    let u = |f: &dyn Fn(&Edge) -> u32| -> ArrayRef {
        Arc::new(UInt32Array::from_iter_values(edges.iter().map(f)))
    };
    let fl = |f: &dyn Fn(&Edge) -> f32| -> ArrayRef {
        Arc::new(Float32Array::from_iter_values(edges.iter().map(f)))
    };
    let arrays: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            edges.iter().map(|e| e.target_skill.as_str()),
        )),
        u(&|e| e.target_class),
        Arc::new(StringArray::from_iter_values(
            edges.iter().map(|e| e.src_skill.as_str()),
        )),
        u(&|e| e.src_clip),
        u(&|e| e.src_frame),
        u(&|e| e.dst_clip),
        u(&|e| e.dst_frame),
        Arc::new(Float64Array::from_iter_values(edges.iter().map(|e| e.beta))),
        u(&|e| e.n_masked),
        fl(&|e| e.align_yaw),
        fl(&|e| e.align_dx),
        fl(&|e| e.align_dy),
    ];
    Ok(RecordBatch::try_new(schema_of(&columns()), arrays)?)
}

/// The record batch of the per-skill summaries.
pub fn summary_batch(rows: &[SkillSummary]) -> Result<RecordBatch> {
    let mut hist = ListBuilder::new(UInt32Builder::new()).with_field(Arc::new(Field::new(
        "item",
        DataType::UInt32,
        false,
    )));
    for r in rows {
        hist.values().append_slice(&r.n_hist);
        hist.append(true);
    }
    let arrays: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.target_skill.as_str()),
        )),
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.states))),
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.kept))),
        Arc::new(UInt32Array::from_iter_values(
            rows.iter().map(|r| r.dropped),
        )),
        Arc::new(hist.finish()),
        Arc::new(Float64Array::from(
            rows.iter().map(|r| r.beta_median).collect::<Vec<_>>(),
        )),
    ];
    Ok(RecordBatch::try_new(schema_of(&summary_columns()), arrays)?)
}

/// Read `stg_edges.parquet` back.
pub fn read(path: &std::path::Path) -> Result<Vec<Edge>> {
    let t = super::io::read_parquet(path)?;
    check_table(&t, path, "stg_edges")?;
    let mut out = Vec::new();
    for b in &t.batches {
        let u = |n: &str| -> Result<Vec<u32>> {
            Ok(col(b, n, path)?
                .as_primitive::<UInt32Type>()
                .values()
                .to_vec())
        };
        let fl = |n: &str| -> Result<Vec<f32>> {
            Ok(col(b, n, path)?
                .as_primitive::<Float32Type>()
                .values()
                .to_vec())
        };
        let (ts, ss) = (strs(b, "target_skill", path)?, strs(b, "src_skill", path)?);
        let (tc, sc, sf, dc, df, nm) = (
            u("target_class")?,
            u("src_clip")?,
            u("src_frame")?,
            u("dst_clip")?,
            u("dst_frame")?,
            u("n_masked")?,
        );
        let beta = col(b, "beta", path)?
            .as_primitive::<Float64Type>()
            .values()
            .to_vec();
        let (yaw, dx, dy) = (fl("align_yaw")?, fl("align_dx")?, fl("align_dy")?);
        for i in 0..b.num_rows() {
            out.push(Edge {
                target_skill: ts[i].clone(),
                target_class: tc[i],
                src_skill: ss[i].clone(),
                src_clip: sc[i],
                src_frame: sf[i],
                dst_clip: dc[i],
                dst_frame: df[i],
                beta: beta[i],
                n_masked: nm[i],
                align_yaw: yaw[i],
                align_dx: dx[i],
                align_dy: dy[i],
            });
        }
    }
    Ok(out)
}

/// Read `input/stg_edges.parquet` and check it against the clips of `lib`
/// (same ingest id, every edge's clips, frames and target skill); `p_e` is
/// named in the error when the table is missing.
///
/// # Errors
/// A missing or unreadable table, one of another ingest, or an edge that
/// does not fit the clips.
pub fn load_edges(input: &Path, lib: &crate::motion::MotionLib, p_e: f64) -> Result<Vec<Edge>> {
    let path = input.join("stg_edges.parquet");
    if !path.is_file() {
        bail!(
            "{} does not exist: p_e = {p_e} starts trajectories from the Stitched Trajectory Graph; \
             run `skillaug build-stg --out {}` first (or set sample-stf.p_e=0)",
            path.display(),
            input.display()
        );
    }
    let edges = read(&path)?;
    super::check_ingest_id(
        &path,
        &super::ingest_id(&input.join("clips.parquet"))?,
        "build-stg",
    )?;
    for (i, e) in edges.iter().enumerate() {
        let ok = |c: u32, f: u32| {
            lib.frames
                .get(c as usize)
                .is_some_and(|cf| (f as usize) < cf.frames)
        };
        if !ok(e.src_clip, e.src_frame)
            || !ok(e.dst_clip, e.dst_frame)
            || lib.clips[e.dst_clip as usize].skill != e.target_skill
        {
            bail!(
                "{}: row {i} (clip {} frame {} -> clip {} frame {}, skill {}) does not match the clips of {}: \
                 run `skillaug build-stg` again",
                path.display(),
                e.src_clip,
                e.src_frame,
                e.dst_clip,
                e.dst_frame,
                e.target_skill,
                input.display()
            );
        }
    }
    Ok(edges)
}
