//! `pixl models`: the released weights the toolkit uses (the estimators and the PIXLRelight
//! checkpoint): which exist (`list`), where they are (`path`, and `path --verify` to re-check
//! files against their pinned SHA-256), and getting them once (`fetch`, which checks a pinned
//! digest after the download and keeps nothing that differs); the shared flags and the console
//! output are in `crate::weights`. Results go to stdout, notices and progress to stderr; a
//! failure (not on disk, a digest that differs) exits with status 1.
//!
//! `inspect` compares a weights file with what the loader expects (`pixl_model::official`: the
//! released checkpoint's rename table, or our own format) and prints a report for a bug report;
//! it exits 1 on any mismatch.
//!
//! Lookup order and environment variables: see `pixl_estimate::hub` (models folder, then the
//! Hugging Face cache, then a download; `--offline` never touches the network).
use crate::weights::{resolve, verify, WeightsArgs};
use crate::Ctx;
use pixl_estimate::hub::{self, Resolved};

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Every known model: name, repository, licence, size, and whether (and where) it is on disk.
    #[command(after_help = "Examples:\n  pixl models list\n  pixl models list --json --models ~/weights")]
    List(ListArgs),
    /// Download a model once (prints its licence and size first); does nothing if it is on disk.
    ///
    /// A file whose SHA-256 the registry pins (pixlrelight's) is checked after the download; if
    /// it differs, the file is deleted, nothing is kept, and the command fails naming the file and
    /// both digests. Files already on disk are not re-read: `pixl models path NAME --verify` does that.
    #[command(
        after_help = "Examples:\n  pixl models fetch da3-metric\n  pixl models fetch da3-metric --models ~/weights   # into ~/weights (Hugging Face layout)\n  \
pixl models fetch pixlrelight                      # CC BY-NC 4.0: non-commercial use only\n\n\
Then, on a machine without network: pixl reconstruct --image photo.jpg -o scene/ --models ~/weights --offline"
    )]
    Fetch(FetchArgs),
    /// The folder holding a model's files (fails if it is not on disk; never downloads).
    ///
    /// With --verify, every file whose SHA-256 the registry pins is read and checked first (seconds
    /// per GB); the command fails naming the first file that differs. Delete that file and run
    /// `pixl models fetch NAME` to download it again.
    #[command(
        after_help = "Examples:\n  pixl models path da3-metric\n  pixl models path da3-mono --json\n  \
pixl models path pixlrelight --verify           # re-check config.yaml and model.safetensors"
    )]
    Path(PathArgs),
    /// Compare a weights file with what the loader expects: tensors matched, in the file but
    /// unused, expected but missing, mis-shaped; the network the file describes and its parameters
    /// per part; every disagreement with config.yaml. Exit 1 on any mismatch.
    ///
    /// For the paper's released checkpoint the names go through the rename table
    /// (crates/pixl-model/src/official/names.toml, unverified against the released file until
    /// someone with hub access runs this); paste the output into a bug report. Our own checkpoints
    /// are recognised by their metadata and checked against their stored config.
    #[command(
        after_help = "Examples:\n  pixl models inspect pixlrelight          # the release, once fetched\n  \
pixl models inspect ~/dl/model.safetensors --config ~/dl/config.yaml\n  \
pixl models inspect model.safetensors --names my-names.toml   # try a corrected rename table\n  \
pixl models inspect pixl-gpu.safetensors --json"
    )]
    Inspect(InspectArgs),
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
    /// Check the files against the SHA-256 the registry pins for them (files without one are not
    /// read); exit 1 naming a file that differs.
    #[arg(long)]
    pub verify: bool,
}

#[derive(clap::Args, Debug)]
pub struct InspectArgs {
    /// A .safetensors file, or a registry name (`pixlrelight`) whose files are on disk.
    pub file: String,
    /// The release's config.yaml. Default: config.yaml beside the file, if there is one.
    #[arg(long, value_name = "YAML")]
    pub config: Option<std::path::PathBuf>,
    /// A rename table to use instead of the built-in one (same layout as names.toml; also
    /// PIXL_OFFICIAL_NAMES).
    #[arg(long, value_name = "TOML")]
    pub names: Option<std::path::PathBuf>,
    #[command(flatten)]
    pub weights: WeightsArgs,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::List(a) => list(a, ctx),
        Command::Fetch(a) => fetch(a, ctx),
        Command::Path(a) => path(a, ctx),
        Command::Inspect(a) => inspect(a),
    }
}

fn inspect(args: InspectArgs) -> anyhow::Result<()> {
    use pixl_model::official;
    let given = std::path::PathBuf::from(&args.file);
    let weights = if given.exists() {
        given
    } else if let Ok(spec) = hub::lookup(&args.file) {
        let hub = args.weights.hub();
        let r = hub.locate(spec)?.ok_or_else(|| hub.not_on_disk_error(spec))?;
        let file = spec
            .files
            .iter()
            .find(|f| f.path.ends_with(".safetensors"))
            .ok_or_else(|| anyhow::anyhow!("{}: no .safetensors file in its registry entry", spec.name))?;
        r.file(file.path)
    } else {
        anyhow::bail!(
            "{}: no such file, and not a model name (see `pixl models list`)",
            args.file
        );
    };
    let config = args.config.clone().or_else(|| official::config_beside(&weights));
    if let Some(c) = args.config.as_ref().filter(|c| !c.is_file()) {
        anyhow::bail!("--config {}: no such file", c.display());
    }
    let table = official::name_table(args.names.as_deref())?;
    let report = official::inspect(&weights, config.as_deref(), &table)?;
    if args.json {
        let mut v = serde_json::to_value(&report)?;
        v["ok"] = report.ok().into();
        v["problem_lines"] = report.problem_lines().into();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        print!("{}", report.to_text());
    }
    if !report.ok() {
        anyhow::bail!(
            "{}: {} problem(s) against the loader's expectations (listed above)",
            weights.display(),
            report.problem_lines().len().max(1)
        );
    }
    Ok(())
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
                    "sha256": s.files.iter().filter_map(|f| Some((f.path.to_string(), f.sha256?.into()))).collect::<serde_json::Map<String, serde_json::Value>>(),
                    "purpose": s.purpose,
                    "present": present,
                    "dir": if *present { serde_json::Value::from(place.as_str()) } else { serde_json::Value::Null },
                    "problem": if !*present && !place.is_empty() { serde_json::Value::from(place.as_str()) } else { serde_json::Value::Null },
                })
            })
            .collect();
        return ctx.print_json(&serde_json::Value::Array(v));
    }
    // Columns as wide as their longest entry (counted in characters: licences may hold a dash).
    let width = |head: &str, f: fn(&hub::ModelSpec) -> &str| {
        hub::REGISTRY
            .iter()
            .map(|s| f(s).chars().count())
            .chain([head.len()])
            .max()
            .unwrap_or(0)
    };
    let (wn, wr, wl) = (
        width("name", |s| s.name),
        width("repository", |s| s.repo),
        width("licence", |s| s.licence),
    );
    ctx.say(format!(
        "{:<wn$} {:<wr$} {:<wl$} {:>8}  {}",
        "name", "repository", "licence", "size", "on disk"
    ));
    for (s, present, place) in &rows {
        let status = match (present, place.is_empty()) {
            (true, _) => place.clone(),
            (false, true) => "no (`pixl models fetch` or a download on first use)".into(),
            (false, false) => place.clone(),
        };
        ctx.say(format!(
            "{:<wn$} {:<wr$} {:<wl$} {:>8}  {status}",
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

fn path(args: PathArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let spec = hub::lookup(&args.name)?;
    let hub = args.weights.hub();
    let r = hub.locate(spec)?.ok_or_else(|| hub.not_on_disk_error(spec))?;
    // Checked before anything is printed: a folder on stdout means its pinned files match.
    let checks = if args.verify { Some(verify(&r, ctx)?) } else { None };
    if let Some(checks) = checks.as_ref().filter(|_| !ctx.quiet) {
        for c in checks {
            match &c.sha256 {
                Some(d) => eprintln!("{}: sha256 {d} matches", c.file),
                None => eprintln!("{}: no sha256 pinned, not checked", c.file),
            }
        }
    }
    if args.json {
        let mut v = resolved_json(&r);
        if let Some(checks) = &checks {
            // Per file: its digest (equal to the pinned one), or null where none is pinned.
            let verified: serde_json::Map<String, serde_json::Value> = checks
                .iter()
                .map(|c| (c.file.to_string(), c.sha256.clone().into()))
                .collect();
            v["verified"] = verified.into();
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("{}", r.dir.display());
    }
    Ok(())
}
