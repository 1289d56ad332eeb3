//! `skillaug schema NAME`: print a table's columns, one per line.

use crate::table;

/// Print the schema text of `table`.
pub fn run(table: table::Table) {
    print!("{}", table::schema_text(table));
}
