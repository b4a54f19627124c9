//! `pixl models`: the pretrained estimators' weights: which exist (`list`), where they are
//! (`path`), and getting them once (`fetch`); the shared flags and the download's console output
//! are in `crate::weights`.
//!
//! Lookup order and environment variables: see `pixl_estimate::hub` (models folder, then the
//! Hugging Face cache, then a download; `--offline` never touches the network).
use crate::weights::{resolve, WeightsArgs};
use crate::Ctx;
use pixl_estimate::hub::{self, Resolved};

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Every known model: name, repository, licence, size, and whether (and where) it is on disk.
    #[command(after_help = "Examples:\n  pixl models list\n  pixl models list --json --models ~/weights")]
    List(ListArgs),
    /// Download a model once (prints its licence and size first); does nothing if it is on disk.
    #[command(
        after_help = "Examples:\n  pixl models fetch da3-metric\n  pixl models fetch da3-metric --models ~/weights   # into ~/weights (Hugging Face layout)\n\n\
Then, on a machine without network: pixl reconstruct --image photo.jpg -o scene/ --models ~/weights --offline"
    )]
    Fetch(FetchArgs),
    /// The folder holding a model's files (fails if it is not on disk; never downloads).
    #[command(after_help = "Examples:\n  pixl models path da3-metric\n  pixl models path da3-mono --json")]
    Path(PathArgs),
}

#[derive(clap::Args, Debug)]
pub struct ListArgs {
    #[command(flatten)]
    pub weights: WeightsArgs,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct FetchArgs {
    /// Model name (see `pixl models list`).
    pub name: String,
    #[command(flatten)]
    pub weights: WeightsArgs,
}

#[derive(clap::Args, Debug)]
pub struct PathArgs {
    /// Model name (see `pixl models list`).
    pub name: String,
    #[command(flatten)]
    pub weights: WeightsArgs,
    /// Print JSON (folder, files, source) instead of the folder alone.
    #[arg(long)]
    pub json: bool,
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::List(a) => list(a, ctx),
        Command::Fetch(a) => fetch(a, ctx),
        Command::Path(a) => path(a),
    }
}

fn resolved_json(r: &Resolved) -> serde_json::Value {
    let files: serde_json::Map<String, serde_json::Value> = r
        .spec
        .files
        .iter()
        .map(|f| (f.path.to_string(), r.file(f.path).display().to_string().into()))
        .collect();
    serde_json::json!({
        "name": r.spec.name,
        "dir": r.dir.display().to_string(),
        "files": files,
        "source": r.source.to_string(),
    })
}

fn list(args: ListArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let hub = args.weights.hub();
    let mut rows = Vec::new();
    for spec in hub::REGISTRY {
        // A half-copied models folder is reported in the row, not as a failure of `list`.
        let (present, place) = match hub.locate(spec) {
            Ok(Some(r)) => (true, r.dir.display().to_string()),
            Ok(None) => (false, String::new()),
            Err(e) => (false, format!("incomplete: {e}")),
        };
        rows.push((spec, present, place));
    }
    if args.json {
        let v: Vec<serde_json::Value> = rows
            .iter()
            .map(|(s, present, place)| {
                serde_json::json!({
                    "name": s.name,
                    "repo": s.repo,
                    "revision": s.revision,
                    "licence": s.licence,
                    "licence_url": s.licence_url,
                    "approx_bytes": s.approx_bytes(),
                    "files": s.files.iter().map(|f| f.path).collect::<Vec<_>>(),
                    "purpose": s.purpose,
                    "present": present,
                    "dir": if *present { serde_json::Value::from(place.as_str()) } else { serde_json::Value::Null },
                    "problem": if !*present && !place.is_empty() { serde_json::Value::from(place.as_str()) } else { serde_json::Value::Null },
                })
            })
            .collect();
        return ctx.print_json(&serde_json::Value::Array(v));
    }
    ctx.say(format!(
        "{:<12} {:<32} {:<11} {:>8}  {}",
        "name", "repository", "licence", "size", "on disk"
    ));
    for (s, present, place) in &rows {
        let status = match (present, place.is_empty()) {
            (true, _) => place.clone(),
            (false, true) => "no (`pixl models fetch` or a download on first use)".into(),
            (false, false) => place.clone(),
        };
        ctx.say(format!(
            "{:<12} {:<32} {:<11} {:>8}  {status}",
            s.name,
            s.repo,
            s.licence,
            hub::human_bytes(s.approx_bytes())
        ));
    }
    for s in hub::REGISTRY {
        ctx.say(format!("  {}: {}", s.name, s.purpose));
    }
    Ok(())
}

fn fetch(args: FetchArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let spec = hub::lookup(&args.name)?;
    let hub = args.weights.hub();
    let r = resolve(&hub, spec, ctx)?;
    ctx.say(format!("{}: {} ({})", spec.name, r.dir.display(), r.source));
    Ok(())
}

fn path(args: PathArgs) -> anyhow::Result<()> {
    let spec = hub::lookup(&args.name)?;
    let hub = args.weights.hub();
    let r = hub.locate(spec)?.ok_or_else(|| hub.not_on_disk_error(spec))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&resolved_json(&r))?);
    } else {
        println!("{}", r.dir.display());
    }
    Ok(())
}
