//! `pixl bench` (placeholder until its issue lands).
use crate::Ctx;

#[derive(clap::Subcommand, Debug)]
pub enum Command {}

pub fn run(command: Command, _ctx: &Ctx) -> anyhow::Result<()> {
    match command {}
}
