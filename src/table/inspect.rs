//! The summary `skillaug inspect FILE` prints of any skillaug Parquet file,
//! computed with polars: rows, clips, skills, frames and the range of every
//! column.
//!
//! A table without a `skill` column but with a `clip_id` (frames.parquet, and
//! the later per-frame tables) is joined to the `clips.parquet` beside it so
//! that frames are counted per skill.

use super::io::{read_frame as read, read_metadata};
use anyhow::Result;
use polars::prelude::{col, len, AnyValue, DataFrame, DataType, ExplodeOptions, IntoLazy};
use std::path::Path;

/// The summary text of `path`.
pub fn summary(path: &Path) -> Result<String> {
    let meta = read_metadata(path)?;
    let get = |k: &str| {
        meta.iter()
            .find(|(key, _)| key == k)
            .map(|(_, v)| v.clone())
    };
    let df = read(path)?;
    let mut out = String::new();
    let table = get("skillaug.table").unwrap_or_else(|| "(not written by skillaug)".into());
    out += &format!("file      {}\n", path.display());
    out += &format!(
        "table     {table}, schema version {}\n",
        get("skillaug.schema_version").unwrap_or_else(|| "?".into())
    );
    for k in ["dataset", "skeleton", "fps", "quaternion_order"] {
        if let Some(v) = get(&format!("skillaug.{k}")) {
            out += &format!("{:<9} {v}\n", k.replace('_', " "));
        }
    }
    out += &format!("rows      {}\ncolumns   {}\n", df.height(), df.width());

    let names: Vec<String> = df
        .get_column_names()
        .iter()
        .map(|s| s.to_string())
        .collect();
    let has = |c: &str| names.iter().any(|n| n == c);
    let mut lf = df.clone().lazy();
    // Tables keyed by a target skill (stg_edges, stf_samples) group by it.
    if !has("skill") && has("target_skill") {
        lf = lf.with_column(col("target_skill").alias("skill"));
    }
    let mut skill_ok = has("skill") || has("target_skill");
    if !skill_ok && has("clip_id") {
        let clips = path.with_file_name("clips.parquet");
        if clips.is_file() && clips != path {
            let c = read(&clips)?.lazy().select([col("clip_id"), col("skill")]);
            lf = lf.left_join(c, col("clip_id"), col("clip_id"));
            skill_ok = true;
        }
    }
    if has("clip_id") {
        out += &format!("clips     {}\n", df.column("clip_id")?.n_unique()?);
    }
    if has("valid") {
        let valid = df.column("valid")?.bool()?.sum().unwrap_or(0);
        out += &format!("frames    {} ({valid} valid)\n", df.height());
    }
    if skill_ok {
        let mut aggs = vec![len().alias("rows")];
        if has("clip_id") {
            aggs.push(col("clip_id").n_unique().alias("clips"));
        }
        if has("valid") {
            aggs.push(col("valid").cast(DataType::UInt32).sum().alias("valid"));
        }
        if has("frames") {
            aggs.push(col("frames").cast(DataType::UInt64).sum().alias("frames"));
        }
        if has("duration_s") {
            aggs.push(col("duration_s").sum().alias("secs"));
        }
        let per = lf
            .group_by([col("skill")])
            .agg(aggs)
            .sort(["skill"], Default::default())
            .collect()?;
        out += &format!(
            "skills    {}\n\nper skill\n{}\n",
            per.height(),
            render(&per)?
        );
    }
    out += &format!("\ncolumns\n{}", ranges(&df)?);
    Ok(out)
}

/// One line per column: type, nulls, and min/max (numbers, flattened lists),
/// true count (booleans) or distinct values (strings).
fn ranges(df: &DataFrame) -> Result<String> {
    let mut s = format!(
        "{:<16} {:<22} {:>7}  {}\n",
        "column", "type", "nulls", "range"
    );
    for c in df.columns() {
        let series = c.as_materialized_series();
        let flat = series.explode(ExplodeOptions {
            empty_as_null: false,
            keep_nulls: false,
        })?;
        let range = match flat.dtype() {
            DataType::Boolean => format!("{} true", flat.bool()?.sum().unwrap_or(0)),
            DataType::String => format!("{} distinct", flat.n_unique()?),
            d if d.is_primitive_numeric() => match (flat.min::<f64>()?, flat.max::<f64>()?) {
                (Some(lo), Some(hi)) => format!("{} .. {}", num(lo), num(hi)),
                _ => "empty".into(),
            },
            _ => String::new(),
        };
        s += &format!(
            "{:<16} {:<22} {:>7}  {range}\n",
            c.name(),
            format!("{}", series.dtype()),
            series.null_count()
        );
    }
    Ok(s)
}

/// Plain aligned text of a small frame (polars' own display truncates).
fn render(df: &DataFrame) -> Result<String> {
    let cols = df.columns();
    let cells: Vec<Vec<String>> = cols
        .iter()
        .map(|c| {
            let s = c.as_materialized_series();
            (0..s.len())
                .map(|i| match s.get(i) {
                    Ok(AnyValue::String(v)) => v.to_string(),
                    Ok(AnyValue::Float32(v)) => format!("{v:.2}"),
                    Ok(AnyValue::Float64(v)) => format!("{v:.2}"),
                    Ok(v) => v.to_string(),
                    Err(_) => "?".into(),
                })
                .collect()
        })
        .collect();
    let widths: Vec<usize> = cols
        .iter()
        .zip(&cells)
        .map(|(c, v)| {
            v.iter()
                .map(|x| x.len())
                .chain([c.name().len()])
                .max()
                .unwrap_or(0)
        })
        .collect();
    let mut s = String::new();
    let left: Vec<bool> = cols
        .iter()
        .map(|c| c.dtype() == &DataType::String)
        .collect();
    let cell = |text: &str, w: usize, left: bool| {
        if left {
            format!("{text:<w$}  ")
        } else {
            format!("{text:>w$}  ")
        }
    };
    for ((c, w), l) in cols.iter().zip(&widths).zip(&left) {
        s += &cell(c.name().as_str(), *w, *l);
    }
    s = s.trim_end().to_string() + "\n";
    for r in 0..df.height() {
        let mut line = String::new();
        for ((v, w), l) in cells.iter().zip(&widths).zip(&left) {
            line += &cell(&v[r], *w, *l);
        }
        s += line.trim_end();
        s += "\n";
    }
    Ok(s)
}

/// Six decimals, or scientific notation for magnitudes below 1e-3.
fn num(v: f64) -> String {
    if v != 0.0 && v.abs() < 1e-3 {
        format!("{v:.3e}")
    } else {
        format!("{v:.6}")
    }
}
