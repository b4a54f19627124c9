//! `pixl weights`: split a weights file into parts of bounded size (`split`, optionally as
//! f16/bf16) and join parts back into one file (`join`); the work is `pixl_model::parts`.
use crate::Ctx;
use anyhow::Context;
use candle_core::DType;
use pixl_model::parts::{self, Overwrite, SplitOptions};
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Split a weights file into parts of at most --max-part-mib each, named
    /// `<stem>-00001-of-0000N.safetensors` (optionally converted to f16/bf16 first). Tensors go
    /// into parts whole; each part records its index, the count and an id of the whole split.
    #[command(after_help = "Examples:\n  pixl weights split W.safetensors -o parts/\n  \
pixl weights split W.safetensors --dtype bf16 --max-part-mib 16 -o parts/ --json\n\n\
Without --dtype conversion, `pixl weights join` gives back the file byte for byte. Parts of the same\n\
stem already in the folder are refused; with --force the new set replaces them (and parts of an\n\
earlier split with another count are removed), so the folder holds one set.")]
    Split(SplitArgs),
    /// Join the parts of one split back into one weights file. The parts may come in any order;
    /// one part stands for its whole set (the others are looked for beside it, by name).
    #[command(
        after_help = "Examples:\n  pixl weights join parts/*.safetensors -o W.safetensors\n  \
pixl weights join parts/W-00001-of-00004.safetensors -o W.safetensors --json\n\n\
The parts must form one complete set: one split id, every index once, the stored config's tensors\n\
exactly, and the hash recorded at the split (a part changed in transit is refused)."
    )]
    Join(JoinArgs),
}

/// `--dtype` values: keep the file's, or convert every tensor.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum DtypeArg {
    Keep,
    F32,
    F16,
    Bf16,
}

impl DtypeArg {
    fn dtype(self) -> Option<DType> {
        match self {
            DtypeArg::Keep => None,
            DtypeArg::F32 => Some(DType::F32),
            DtypeArg::F16 => Some(DType::F16),
            DtypeArg::Bf16 => Some(DType::BF16),
        }
    }
}

#[derive(clap::Args, Debug)]
pub struct SplitArgs {
    /// The weights file (.safetensors, as `pixl train` or `pixl model init` write them).
    pub input: PathBuf,
    /// Output folder for the parts (created if missing).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Dtype of the parts' tensors: keep the file's, or convert (round to nearest even).
    #[arg(long, value_enum, default_value_t = DtypeArg::Keep)]
    pub dtype: DtypeArg,
    /// Largest part, in MiB (whole file: header and data); fractions allowed.
    #[arg(long, default_value = "16", value_parser = parse_mib)]
    pub max_part_mib: f64,
    /// Replace parts of the same stem already in the output folder.
    #[arg(long)]
    pub force: bool,
    /// Print JSON (`parts`: path, bytes, tensors; `dtype`, …) instead of a summary.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct JoinArgs {
    /// The parts (any order), or one of them.
    #[arg(required = true, num_args = 1..)]
    pub parts: Vec<PathBuf>,
    /// Output .safetensors file.
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Replace the output file if it exists (never one of the parts).
    #[arg(long)]
    pub force: bool,
    /// Print JSON (`output`, `bytes`, `tensors`, `dtype`, …) instead of a summary.
    #[arg(long)]
    pub json: bool,
}

const MIB: f64 = 1024.0 * 1024.0;

/// A positive size in MiB (at most 1 TiB).
fn parse_mib(s: &str) -> Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|_| format!("{s:?} is not a number"))?;
    if !v.is_finite() || v * MIB < 1.0 {
        return Err("must be a positive size in MiB (e.g. 16 or 0.5)".into());
    }
    if v > 1024.0 * 1024.0 {
        return Err("must be at most 1048576 (1 TiB)".into());
    }
    Ok(v)
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::Split(a) => split(a, ctx),
        Command::Join(a) => join(a, ctx),
    }
}

fn overwrite(force: bool) -> Overwrite {
    if force {
        Overwrite::Allow
    } else {
        Overwrite::Refuse
    }
}

/// As the weights' metadata spells it: `F32`, `F16`, `BF16`.
fn dtype_name(d: DType) -> String {
    d.as_str().to_ascii_uppercase()
}

fn mib(bytes: u64) -> String {
    format!("{:.2} MiB", bytes as f64 / MIB)
}

fn split(args: SplitArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    if args.out.exists() && !args.out.is_dir() {
        anyhow::bail!("{}: is a file; -o takes the folder the parts go to", args.out.display());
    }
    let opts = SplitOptions {
        dtype: args.dtype.dtype(),
        max_part_bytes: (args.max_part_mib * MIB) as u64,
        overwrite: overwrite(args.force),
    };
    // The library's errors name the file (and the tensor or part).
    let done = parts::split(&args.input, &args.out, &opts)?;
    if args.json {
        let list: Vec<serde_json::Value> = done
            .parts
            .iter()
            .map(|p| serde_json::json!({ "path": p.path, "bytes": p.bytes, "tensors": p.tensors }))
            .collect();
        return ctx.print_json(&serde_json::json!({
            "input": args.input,
            "out_dir": args.out,
            "source_dtype": dtype_name(done.source_dtype),
            "dtype": dtype_name(done.dtype),
            "max_part_bytes": opts.max_part_bytes,
            "parts_id": done.parts_id,
            "parts": list,
            "removed": done.removed,
        }));
    }
    let conversion = if done.dtype == done.source_dtype {
        dtype_name(done.dtype)
    } else {
        format!("{}, from {}", dtype_name(done.dtype), dtype_name(done.source_dtype))
    };
    let n = done.parts.len();
    ctx.say(format!(
        "wrote {n} part{} of {} ({conversion}) in {}, each at most {}:",
        if n == 1 { "" } else { "s" },
        args.input.display(),
        args.out.display(),
        mib(opts.max_part_bytes)
    ));
    for p in &done.parts {
        let name = p.path.file_name().unwrap_or_default().to_string_lossy();
        ctx.say(format!("  {name}  {:>10}  {:>5} tensors", mib(p.bytes), p.tensors));
    }
    if !done.removed.is_empty() {
        ctx.say(format!("removed {} parts of an earlier split", done.removed.len()));
    }
    Ok(())
}

fn join(args: JoinArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    let inputs: Vec<&std::path::Path> = args.parts.iter().map(|p| p.as_path()).collect();
    pixl_core::output::check_output(&args.out, &["safetensors"], &inputs)?;
    let done = parts::join(&args.parts, &args.out, overwrite(args.force))
        .with_context(|| format!("joining parts into {}", args.out.display()))?;
    if args.json {
        return ctx.print_json(&serde_json::json!({
            "output": done.output,
            "bytes": done.bytes,
            "tensors": done.tensors,
            "dtype": dtype_name(done.dtype),
            "parts": done.parts,
            "parts_id": done.parts_id,
        }));
    }
    let n = done.parts.len();
    ctx.say(format!(
        "wrote {} from {n} part{} ({}, {} tensors, {})",
        done.output.display(),
        if n == 1 { "" } else { "s" },
        mib(done.bytes),
        done.tensors,
        dtype_name(done.dtype)
    ));
    Ok(())
}
