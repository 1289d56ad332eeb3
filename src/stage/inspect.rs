//! `skillaug inspect FILE`: summarise any skillaug Parquet file (rows,
//! clips, skills, frames and the range of every column; the summary is
//! [`crate::table::inspect::summary`]).

use anyhow::Result;
use std::path::Path;

/// Print the summary of `path`.
pub fn run(path: &Path) -> Result<()> {
    print!("{}", crate::table::inspect::summary(path)?);
    Ok(())
}
