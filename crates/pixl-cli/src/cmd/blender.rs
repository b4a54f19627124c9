//! `pixl blender export scene.toml -o scene.py`: the Blender bridge. The script
//! rebuilds the scene in Blender and renders Cycles' passes into a multilayer EXR; see
//! `pixl_render::blender` for the mapping. Run it with
//! `blender -b -P scene.py -- --out passes.exr --spp N` or `python scene.py --out passes.exr --spp N`.
use crate::Ctx;
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Write a Blender Python script (+ a `<name>_data/` folder of meshes and textures beside it).
    Export(ExportArgs),
}

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Example:\n  pixl blender export scene/scene.toml -o scene.py\n  blender -b -P scene.py -- --out passes.exr --spp 64   # or: python scene.py --out passes.exr (with PyPI bpy)"
)]
pub struct ExportArgs {
    /// The scene (.toml or .json).
    pub scene: PathBuf,
    /// The script to write (.py).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::Export(a) => {
            pixl_core::output::check_output(&a.out, &["py"], &[&a.scene])?;
            let scene = pixl_render::Scene::load(&a.scene)?;
            let e = pixl_render::blender::export_blender(&scene, &a.out)?;
            ctx.say(format!(
                "wrote {} ({} meshes, {} textures in {}); run: blender -b -P {} -- --out passes.exr --spp 64",
                e.script.display(),
                e.meshes,
                e.textures,
                e.data_dir.display(),
                e.script.display()
            ));
            Ok(())
        }
    }
}
