//! `pixl render` (placeholder until its issue lands).
use crate::Ctx;

#[derive(clap::Args, Debug)]
pub struct Args {}

pub fn run(_args: Args, _ctx: &Ctx) -> anyhow::Result<()> {
    anyhow::bail!("`pixl render` is not available in this build yet")
}
