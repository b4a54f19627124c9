//! `pixl light add`: add a preset's lights or one light spelled out on the command line to a
//! scene file (rewritten atomically, in place unless `-o` is given).
//!
//! A light's flags are one `pixl_pipeline::lights::LightSpec` (shared with `pixl relight
//! --light '…'`), which says where the light goes (`--position`, `--at-pixel`, `--from`,
//! `--azimuth`/`--elevation`), what it defaults to and what is checked.
use crate::Ctx;
use anyhow::{bail, Context};
use pixl_pipeline::lights::LightSpec;
use pixl_render::presets::{apply_preset, PRESETS};
use pixl_render::Scene;
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Add lights to a scene: a preset of the paper or one light given by flags.
    #[command(after_help = concat!("Examples:\n  \
pixl light add scene.toml --preset cool-side-flash\n  \
pixl light add scene.toml --preset dim-overhead-spot --replace -o lit.toml\n  \
pixl light add scene.toml --type point --at-pixel 320,140                 # 0.15 x diagonal off the surface at that pixel\n  \
pixl light add scene.toml --type spot --from left --elevation 30 --power 500\n  \
pixl light add scene.toml --type area --azimuth 45 --elevation 60 --size 1.5\n  \
pixl light add scene.toml --type sun --from behind --strength 3\n  \
pixl light add scene.toml --type point --power 100 --position 1,3,1 --temperature 3200\n  \
pixl light add scene.toml --type spot --power 500 --position 0,3,2 --look-at 0,0,0 --spot-size 40\n  \
pixl light add scene.toml --type sun --strength 3 --direction -0.3,-1,-0.2 --color 1,0.95,0.9\n\n\
Placement: --at-pixel X,Y is a pixel of the scene's camera image (the photo, for a scene from\n\
`pixl reconstruct`), from its top-left corner. --from left|right|above|below|front|behind, or\n\
--azimuth/--elevation in degrees, go around the centre of the scene's bounds: azimuth 0 is the\n\
camera's side (front), 90 right, 180 behind the scene, -90 left; elevation 90 is straight above.\n\
`pixl scene info scene.toml` prints the bounds, camera and lights.\n\n\
Units as in Blender: power in W (point intensity = P/4π W/sr; area radiance = P/(πA)), sun strength in W/m².\n\n",
crate::scene_axes_help!()))]
    Add(AddArgs),
}

#[derive(clap::Args, Debug)]
pub struct AddArgs {
    /// Scene file (.toml or .json).
    pub scene: PathBuf,
    /// Write here instead of rewriting the scene in place.
    #[arg(short, long)]
    pub out: Option<PathBuf>,
    /// A preset of the paper (§4.2).
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(PRESETS), conflicts_with = "light_type")]
    pub preset: Option<String>,
    /// Remove the scene's existing lights first.
    #[arg(long)]
    pub replace: bool,
    #[command(flatten)]
    pub light: LightSpec,
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    let Command::Add(a) = command;
    match (&a.preset, a.light.is_given()) {
        (Some(_), true) => bail!("--preset adds the preset's own lights; give either --preset or the flags of one light"),
        (None, false) => bail!("give --preset NAME or a light's flags (--type point|spot|area|sun with --position, --at-pixel or --from; see --help)"),
        (None, true) => a.light.check()?,
        (Some(_), false) => {}
    }
    let out = a.out.clone().unwrap_or_else(|| a.scene.clone());
    pixl_core::output::check_output(&out, &["toml", "json"], &[])?;
    let mut scene = Scene::load(&a.scene)?;
    let before = scene.lights.len();
    match &a.preset {
        Some(p) => apply_preset(&mut scene, p, a.replace)?,
        None => {
            let (light, notes) = a.light.build(&scene)?;
            for n in notes {
                ctx.say(n);
            }
            if a.replace {
                scene.lights.clear();
            }
            scene.lights.push(light);
            scene.validate().context("the new light")?;
        }
    }
    // Relative paths in the scene stay valid only if the output sits beside the input.
    let dir = |p: &std::path::Path| std::fs::canonicalize(pixl_core::output::parent_dir(p)).ok();
    if dir(&a.scene) != dir(&out)
        && scene
            .objects
            .iter()
            .any(|o| matches!(&o.shape, pixl_render::Shape::Mesh { path } if path.is_relative()))
    {
        ctx.say(format!(
            "note: {} refers to mesh files relative to {}; keep it beside them",
            out.display(),
            pixl_core::output::parent_dir(&a.scene).display()
        ));
    }
    scene.save(&out)?;
    let added = scene.lights.len() as isize - if a.replace { 0 } else { before as isize };
    ctx.say(format!(
        "{} light(s) added; {} now has {} light(s)",
        added,
        out.display(),
        scene.lights.len()
    ));
    Ok(())
}
