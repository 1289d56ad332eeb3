//! `skillaug sample-stf` (being written).
use super::Common;
use anyhow::{bail, Result};
/// Run the stage.
pub fn run(_common: &Common) -> Result<()> {
    bail!("sample-stf is not finished yet")
}
