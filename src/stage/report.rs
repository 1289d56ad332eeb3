//! `skillaug report`: one or more `eval_summary.parquet` files as tables
//! shaped like the paper's ([`crate::eval::report`]), printed and optionally
//! written as Markdown; `--with-reference` adds the paper's rows.

use crate::eval::report::{
    markdown, merge_summaries, paper_row, paper_table, table, text, trial_notes,
};
use anyhow::Result;
use std::path::{Path, PathBuf};

/// Run the command: read `inputs` (files or folders with eval_summary.parquet).
pub fn run(inputs: &[PathBuf], with_reference: bool, markdown_out: Option<&Path>) -> Result<()> {
    let mut rows = merge_summaries(inputs)?;
    if with_reference {
        rows.extend(paper_table(&rows).iter().map(paper_row));
    }
    let (h, b) = table(&rows);
    print!("{}", text(&h, &b));
    println!("cells: SR % / eps-NSR % / NR; TSR in %");
    let notes = trial_notes(&rows);
    for n in &notes {
        println!("{n}");
    }
    if let Some(m) = markdown_out {
        let mut md = markdown(&h, &b);
        md.push_str("\nCells: SR % / eps-NSR % / NR; TSR in %.\n");
        for n in &notes {
            md.push_str(&format!("\n- {n}"));
        }
        if !notes.is_empty() {
            md.push('\n');
        }
        let mut staged = crate::table::io::Staged::new();
        staged.text(m, &md)?;
        staged.commit()?;
        println!("wrote {}", m.display());
    }
    Ok(())
}
