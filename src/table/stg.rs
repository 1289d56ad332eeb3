//! `stg_edges.parquet` and `stg_summary.parquet`: the Stitched Trajectory
//! Graph (paper Section 4.4, Appendix B.4; reference code:
//! Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/offline_state_search.py`).

use super::columns::{specs, Column, TableRow};
use super::read_util::{check_table, col, strs};
use super::ColumnSpec;
use crate::augment::stg::{Edge, SkillSummary};
use anyhow::{bail, Result};
use arrow::array::AsArray;
use arrow::datatypes::{Float32Type, Float64Type, UInt32Type};
use arrow::record_batch::RecordBatch;
use std::path::Path;

/// One kept connection per row of `stg_edges.parquet`.
impl TableRow for Edge {
    fn columns() -> Vec<Column<Edge>> {
        vec![
            Column::new("target_skill", "skill A whose graph the edge belongs to (the skill to be tracked after the switch)", |e: &Edge| e.target_skill.clone()),
            Column::new("target_class", "class id of A (the condition during the stitched trajectory)", |e: &Edge| e.target_class),
            Column::new("src_skill", "skill of the external start state", |e: &Edge| e.src_skill.clone()),
            Column::new("src_clip", "clip of the external start state (clips.parquet clip_id)", |e: &Edge| e.src_clip),
            Column::new("src_frame", "frame of the external start state", |e: &Edge| e.src_frame),
            Column::new("dst_clip", "clip of A the start connects to", |e: &Edge| e.dst_clip),
            Column::new("dst_frame", "frame of A the start connects to (argmax of S_k)", |e: &Edge| e.dst_frame),
            Column::new("beta", "similarity S_k (Eq. 19) of the aligned start and the target frame, > tau", |e: &Edge| e.beta),
            Column::new("n_masked", "masked states between start and target (Eq. 20)", |e: &Edge| e.n_masked),
            Column::new("align_yaw", "turn about the vertical through the start's root applied to the start state, rad", |e: &Edge| e.align_yaw),
            Column::new("align_dx", "then this x shift, m (start root x -> target root x)", |e: &Edge| e.align_dx),
            Column::new("align_dy", "then this y shift, m", |e: &Edge| e.align_dy),
        ]
    }
}

/// One target skill per row of `stg_summary.parquet`.
impl TableRow for SkillSummary {
    fn columns() -> Vec<Column<SkillSummary>> {
        vec![
            Column::new("target_skill", "skill A", |r: &SkillSummary| r.target_skill.clone()),
            Column::new("states", "external states considered (valid frames of the other skills' clips; per-target mode: frames of A x other skills)", |r: &SkillSummary| r.states),
            Column::new("kept", "edges with beta > tau", |r: &SkillSummary| r.kept),
            Column::new("dropped", "states without a connection (beta <= tau)", |r: &SkillSummary| r.dropped),
            Column::new("n_hist", "kept edges per masked-state count N = 0, 1, ..., N_max", |r: &SkillSummary| r.n_hist.clone()),
            Column::new("beta_median", "median beta of the kept edges", |r: &SkillSummary| r.beta_median),
        ]
    }
}

/// Columns of `stg_edges.parquet`: one kept connection each.
pub fn columns() -> Vec<ColumnSpec> {
    specs::<Edge>()
}

/// Columns of `stg_summary.parquet`: one row per target skill.
pub fn summary_columns() -> Vec<ColumnSpec> {
    specs::<SkillSummary>()
}

/// The record batch of `edges`.
pub fn batch(edges: &[Edge]) -> Result<RecordBatch> {
    super::columns::batch(edges)
}

/// The record batch of the per-skill summaries.
pub fn summary_batch(rows: &[SkillSummary]) -> Result<RecordBatch> {
    super::columns::batch(rows)
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
