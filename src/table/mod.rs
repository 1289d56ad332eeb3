//! The Parquet tables: the only code that builds or reads Arrow arrays.
//!
//! Each table has a documented column list ([`ColumnSpec`]), a schema version
//! and key-value metadata (`skillaug.*` keys). Metadata lives in the Parquet
//! file's key-value list, in a fixed order, rather than in the Arrow schema,
//! whose metadata is a hash map and would make the bytes of a file depend on
//! the process: outputs must be byte-identical for identical inputs.
//! `skillaug schema NAME` prints a table's columns; `schemas/NAME.txt` holds
//! the same text, checked by a test.

pub mod clips;
pub mod columns;
pub mod eval;
pub mod frames;
pub mod he;
pub mod inspect;
pub mod io;
pub mod read_util;
pub mod rollout;
pub mod series;
pub mod stf;
pub mod stg;
pub mod train;

use arrow::datatypes::{DataType, Field, Schema};
use std::sync::Arc;

/// Version of the table layouts written by this build.
pub const SCHEMA_VERSION: u32 = 1;

/// One documented column.
#[derive(Debug, Clone)]
pub struct ColumnSpec {
    /// Column name.
    pub name: &'static str,
    /// Arrow type.
    pub dtype: DataType,
    /// Whether nulls may occur.
    pub nullable: bool,
    /// Meaning and units.
    pub doc: &'static str,
}

impl ColumnSpec {
    /// A column.
    pub fn new(name: &'static str, dtype: DataType, nullable: bool, doc: &'static str) -> Self {
        ColumnSpec {
            name,
            dtype,
            nullable,
            doc,
        }
    }
}

/// `List<Float32>` with non-null items.
pub fn f32_list() -> DataType {
    DataType::List(Arc::new(Field::new("item", DataType::Float32, false)))
}

/// `FixedSizeList<Float32, n>` with non-null items.
pub fn f32_fixed(n: i32) -> DataType {
    DataType::FixedSizeList(Arc::new(Field::new("item", DataType::Float32, false)), n)
}

/// `List<UInt32>` with non-null items.
pub fn u32_list() -> DataType {
    DataType::List(Arc::new(Field::new("item", DataType::UInt32, false)))
}

/// `List<Utf8>` with non-null items.
pub fn str_list() -> DataType {
    DataType::List(Arc::new(Field::new("item", DataType::Utf8, false)))
}

/// The Arrow schema of a column list.
pub fn schema_of(cols: &[ColumnSpec]) -> Arc<Schema> {
    Arc::new(Schema::new(
        cols.iter()
            .map(|c| Field::new(c.name, c.dtype.clone(), c.nullable))
            .collect::<Vec<_>>(),
    ))
}

/// Key-value metadata of a stage's tables: the keys every table carries
/// (schema version, skillaug version, dataset, resolved-settings hash), then
/// the stage's own, all under `skillaug.`; [`Meta::table`] puts
/// `skillaug.table` first.
#[derive(Clone, Debug)]
pub struct Meta(Vec<(String, String)>);

impl Meta {
    /// The common keys for `dataset` and the stage's resolved settings text.
    pub fn new(dataset: &str, resolved: &str) -> Meta {
        Meta(vec![
            ("skillaug.schema_version".into(), SCHEMA_VERSION.to_string()),
            ("skillaug.version".into(), env!("CARGO_PKG_VERSION").into()),
            ("skillaug.dataset".into(), dataset.into()),
            (
                "skillaug.config_hash".into(),
                crate::config::hash_text(resolved),
            ),
        ])
    }

    /// Add `skillaug.<key>` = `value`.
    pub fn with(mut self, key: &str, value: impl Into<String>) -> Meta {
        self.0.push((format!("skillaug.{key}"), value.into()));
        self
    }

    /// The list for table `name`.
    pub fn table(&self, name: &str) -> Vec<(String, String)> {
        let mut v = vec![("skillaug.table".to_string(), name.to_string())];
        v.extend_from_slice(&self.0);
        v
    }
}

/// The identity of one ingest run: a hash of the resolved settings and
/// the source files' hashes that `ingest` records in both of its tables.
/// Later stages record it in theirs (`skillaug.ingest_id`) so that a reader
/// can tell tables of two different runs apart. Empty when the table lacks
/// those keys (rewritten by another tool): then nothing can be checked.
///
/// # Errors
/// The table cannot be read.
pub fn ingest_id(table: &std::path::Path) -> anyhow::Result<String> {
    let meta = io::read_metadata(table)?;
    let get = |k: &str| {
        meta.iter()
            .find(|(key, _)| key == k)
            .map(|(_, v)| v.as_str())
    };
    Ok(
        match (get("skillaug.config_hash"), get("skillaug.source_sha256")) {
            (Some(c), Some(s)) => crate::config::hash_text(&format!("{c}\n{s}")),
            _ => String::new(),
        },
    )
}

/// Whether two ingest ids name different runs (an empty id is unknown and
/// differs from nothing).
pub fn ingest_ids_differ(a: &str, b: &str) -> bool {
    !a.is_empty() && !b.is_empty() && a != b
}

/// Check that the table at `path` (metadata `skillaug.ingest_id`, when it
/// has the key) was made from the clips of ingest run `id` (empty: not
/// known, nothing to check).
///
/// # Errors
/// Names the table, the two ids and what to re-run.
pub fn check_ingest_id(path: &std::path::Path, id: &str, stage: &str) -> anyhow::Result<()> {
    let meta = io::read_metadata(path)?;
    if let Some((_, v)) = meta.iter().find(|(k, _)| k == "skillaug.ingest_id") {
        if ingest_ids_differ(v, id) {
            anyhow::bail!(
                "{} was made from the clips of another ingest run (ingest id {v}) than the \
                 clips read with it ({id}): give the run folder it was made from, or run \
                 `skillaug {stage}` again",
                path.display()
            );
        }
    }
    Ok(())
}

/// Load the ingested clips of a run folder (`clips.parquet`, `frames.parquet`),
/// checked to come from one ingest run and to be usable
/// ([`crate::motion::MotionLib::check`]).
///
/// # Errors
/// A missing or unreadable table, tables of two runs, an unusable clip
/// or a class fault, naming the file and the clip.
pub fn load_library(run: &std::path::Path) -> anyhow::Result<crate::motion::MotionLib> {
    use anyhow::Context;
    let cp = run.join("clips.parquet");
    if !cp.is_file() {
        anyhow::bail!(
            "{} does not exist: run `skillaug ingest --out {}` first",
            cp.display(),
            run.display()
        );
    }
    let fp = run.join("frames.parquet");
    if fp.is_file() {
        let (a, b) = (ingest_id(&cp)?, ingest_id(&fp)?);
        if ingest_ids_differ(&a, &b) {
            anyhow::bail!(
                "{} and {} come from two different ingest runs (ingest ids {a} and {b}): two \
                 runs wrote into one folder; ingest again",
                cp.display(),
                fp.display()
            );
        }
    }
    let clips = clips::read(&cp)?;
    let frames = frames::read(&run.join("frames.parquet"), &clips)
        .with_context(|| format!("loading the clips of {}", run.display()))?;
    let skeleton = clips
        .first()
        .and_then(|c| crate::motion::Skeleton::from_name(&c.skeleton))
        .ok_or_else(|| anyhow::anyhow!("{}: no clips, or an unknown skeleton", cp.display()))?;
    let lib = crate::motion::MotionLib {
        skeleton,
        clips,
        frames,
    };
    lib.check(&format!(
        "{} (clips.parquet, frames.parquet)",
        run.display()
    ))?;
    Ok(lib)
}

/// A table skillaug writes (`skillaug schema NAME`): its name is the file
/// stem (`stg_edges` for `stg_edges.parquet`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
#[value(rename_all = "snake_case")]
pub enum Table {
    /// `clips.parquet`.
    Clips,
    /// `frames.parquet`.
    Frames,
    /// `stg_edges.parquet`.
    StgEdges,
    /// `stg_summary.parquet`.
    StgSummary,
    /// `he_loss.parquet`.
    HeLoss,
    /// `he_embeddings.parquet`.
    HeEmbeddings,
    /// `stf_samples.parquet`.
    StfSamples,
    /// `train_metrics.parquet`.
    TrainMetrics,
    /// `eval_trials.parquet`.
    EvalTrials,
    /// `eval_summary.parquet`.
    EvalSummary,
    /// `eval_rollouts.parquet`.
    EvalRollouts,
}

impl Table {
    /// Every table, in the order `skillaug schema` lists them.
    pub const ALL: [Table; 11] = [
        Table::Clips,
        Table::Frames,
        Table::StgEdges,
        Table::StgSummary,
        Table::HeLoss,
        Table::HeEmbeddings,
        Table::StfSamples,
        Table::TrainMetrics,
        Table::EvalTrials,
        Table::EvalSummary,
        Table::EvalRollouts,
    ];

    /// The name: the file stem and the `skillaug.table` metadata value.
    pub fn name(self) -> &'static str {
        match self {
            Table::Clips => "clips",
            Table::Frames => "frames",
            Table::StgEdges => "stg_edges",
            Table::StgSummary => "stg_summary",
            Table::HeLoss => "he_loss",
            Table::HeEmbeddings => "he_embeddings",
            Table::StfSamples => "stf_samples",
            Table::TrainMetrics => "train_metrics",
            Table::EvalTrials => "eval_trials",
            Table::EvalSummary => "eval_summary",
            Table::EvalRollouts => "eval_rollouts",
        }
    }

    /// The documented columns.
    pub fn columns(self) -> Vec<ColumnSpec> {
        match self {
            Table::Clips => clips::columns(),
            Table::Frames => frames::columns(),
            Table::StgEdges => stg::columns(),
            Table::StgSummary => stg::summary_columns(),
            Table::HeLoss => he::loss_columns(),
            Table::HeEmbeddings => he::embedding_columns(),
            Table::StfSamples => stf::columns(),
            Table::TrainMetrics => train::columns(),
            Table::EvalTrials => eval::trial_columns(),
            Table::EvalSummary => eval::summary_columns(),
            Table::EvalRollouts => rollout::columns(),
        }
    }
}

/// Readable type name: `List<Float32>`, `FixedSizeList<Float32, 3>`, ...
pub fn type_name(t: &DataType) -> String {
    match t {
        DataType::List(f) => format!("List<{}>", type_name(f.data_type())),
        DataType::LargeList(f) => format!("LargeList<{}>", type_name(f.data_type())),
        DataType::FixedSizeList(f, n) => {
            format!("FixedSizeList<{}, {n}>", type_name(f.data_type()))
        }
        other => format!("{other:?}"),
    }
}

/// The schema text of `table`: a header, then one field per line.
pub fn schema_text(table: Table) -> String {
    let (name, cols) = (table.name(), table.columns());
    let mut s = format!(
        "# skillaug table `{name}` (`{name}.parquet`), schema version {SCHEMA_VERSION}\n\
         # name: type, null?  -- meaning\n"
    );
    let w = cols.iter().map(|c| c.name.len()).max().unwrap_or(0);
    for c in &cols {
        let t = format!(
            "{}{}",
            type_name(&c.dtype),
            if c.nullable { ", nullable" } else { "" }
        );
        s.push_str(&format!("{:<w$}: {:<36} -- {}\n", c.name, t, c.doc));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_names_are_their_clap_values() {
        use clap::ValueEnum;
        for t in Table::ALL {
            assert_eq!(t.to_possible_value().unwrap().get_name(), t.name());
        }
        assert_eq!(Table::value_variants().len(), Table::ALL.len());
    }

    #[test]
    fn schema_golden_files_match() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas");
        for table in Table::ALL {
            let name = table.name();
            let want = std::fs::read_to_string(dir.join(format!("{name}.txt")))
                .unwrap_or_else(|e| panic!("schemas/{name}.txt: {e}"));
            assert_eq!(
                schema_text(table),
                want,
                "schemas/{name}.txt differs from `skillaug schema {name}`: \
                 re-bless with `skillaug schema {name} > schemas/{name}.txt` if the change is intended"
            );
        }
    }
}
