//! `skillaug schema NAME`: print a table's columns, one per line.

use crate::table;
use anyhow::{anyhow, Result};

/// Print the schema text of table `name`.
pub fn run(name: &str) -> Result<()> {
    let text = table::schema_text(name).ok_or_else(|| {
        anyhow!(
            "unknown table `{name}` (known: {})",
            table::TABLES.join(", ")
        )
    })?;
    print!("{text}");
    Ok(())
}
