//! `pixl eval`: score a model and baselines on a paired dataset (paper §4.1). A thin layer over
//! `pixl_eval::run_eval`: it opens the dataset, builds the pair list and the methods, runs, prints
//! the table and writes `results.md`, `results.json` and `per_pair.csv` into `--out`, and the
//! contact sheet (`--sheet`) where asked.
use crate::Ctx;
use candle_core::DType;
use pixl_data::Split;
use pixl_eval::{baselines::Method, EvalOptions, Lpips, ModelMethod};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
#[command(
    after_help = concat!("Examples:\n  pixl eval --dataset miiw:/data/miiw --weights model.safetensors --lpips alex_lpips.safetensors --out eval-miiw\n  \
pixl eval --dataset folder:shots --baselines identity,compose --pairs pairs.csv --out eval-shots\n  \
pixl eval --dataset synth:held-out --ct coarse --weights run/final.safetensors --weights assets/demo-weights/pixl-tiny-synth.safetensors \
--baselines identity,compose-camera --sheet eval-new/sheet.png --out eval-new\n\n",
crate::dataset_kinds_help!())
)]
pub struct Args {
    /// Dataset as KIND:ROOT (miiw, miiw@MIP, bigtime, vidit, folder, synth; layouts below).
    #[arg(long)]
    pub dataset: String,
    /// Which scenes: test (default; MIIW: the 30 `everett*` scenes), train or all.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// PIXLRelight checkpoint (.safetensors) to evaluate; repeat it to compare several in one
    /// run (`--weights A.safetensors --weights B.safetensors`). One file is the row "Ours";
    /// several are "Ours (<file stem>)" each, so their file stems must differ.
    #[arg(long)]
    pub weights: Vec<PathBuf>,
    /// Baselines, comma-separated: identity (the source), compose (A⊙S+R of C_T, clipped, sRGB),
    /// compose-reinhard (A⊙S+R shown with Reinhard auto-exposure, as `pixl synth --style boxes`
    /// shows its images), compose-camera (with a camera's tone curve, as the photo style does).
    /// Empty for none.
    #[arg(long, default_value = "identity,compose")]
    pub baselines: String,
    /// Pair list, CSV `scene,source,target` (image file names). Default: per scene, image i → i+1 (mod n).
    #[arg(long)]
    pub pairs: Option<PathBuf>,
    /// Which target intrinsics C_T the network and compose get: `exact` (the target's own, as
    /// stored with the dataset) or `coarse` (synthetic sets made with `pixl synth --coarse`: the
    /// coarse reconstruction of the *source* rendered under the target's lights — the paper's
    /// inference setting; `<target>.from_<source>.intrinsics.exr`).
    #[arg(long, default_value = "exact", value_parser = ["exact", "coarse"])]
    pub ct: String,
    /// Skip the light-response score. By default it is computed whenever every pair has what it
    /// needs: with `--ct coarse`, the coarse C_T and path-traced render of the source's own
    /// lighting and of the target's (`pixl synth --coarse` writes both); with `--ct exact`, the
    /// source's and the target's own C_T (the images themselves are the renders).
    #[arg(long)]
    pub no_response: bool,
    /// Evaluate only the first N pairs of the list.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Score raw predictions (no per-channel least-squares scale correction).
    #[arg(long)]
    pub no_scale_correction: bool,
    /// LPIPS v0.1 weights (one safetensors file: torchvision `features.*` + `lin0..4.model.1.weight`).
    /// Without it LPIPS is reported as absent.
    #[arg(long)]
    pub lpips: Option<PathBuf>,
    /// Output folder for results.md, results.json, per_pair.csv (created if missing; those three
    /// files are replaced atomically).
    #[arg(long, default_value = "eval-out")]
    pub out: PathBuf,
    /// Write a contact sheet (PNG) of the first --sheet-pairs pairs: one row per pair, columns
    /// source | C_T albedo | C_T shading | C_T residual | each method's prediction, in table order |
    /// target. The C_T columns appear only when some method reads C_T, each map clipped to
    /// [0, 1] and sRGB-encoded; predictions are shown as scored (after the scale correction unless
    /// --no-scale-correction). No labels are drawn: results.md and results.json (`sheet_columns`)
    /// list the columns. Rows of other sizes are padded on the right with grey.
    #[arg(long)]
    pub sheet: Option<PathBuf>,
    /// Pairs (rows) of the --sheet contact sheet: the first N of the list.
    #[arg(long, default_value_t = 4, requires = "sheet",
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub sheet_pairs: usize,
    /// Print the JSON summary (method rows) on stdout instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Device for the network: cpu, or cuda[:N] (needs a CUDA build: scripts/cuda-setup.sh; `pixl doctor` lists devices).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Network dtype: f32 or bf16.
    #[arg(long, default_value = "f32")]
    pub dtype: String,
    /// Evaluate the network with 8-bit linear layers (CPU f32 with AVX-512 VNNI), as
    /// `pixl relight --int8` runs it; applies to every --weights ("Ours (int8)", "Ours (<stem>, int8)").
    #[arg(long, requires = "weights")]
    pub int8: bool,
    /// Longest side the network works at, as `pixl relight --max-side`: larger pairs are
    /// area-averaged to it and the network's gain and bias applied at the image's own size.
    /// Default: every pair at its own size.
    #[arg(long, requires = "weights", value_parser = clap::value_parser!(u32).range(8..))]
    pub max_side: Option<u32>,
    /// Timing protocol: untimed warm-ups.
    #[arg(long, default_value_t = pixl_eval::DEFAULT_WARMUPS)]
    pub warmups: usize,
    /// Timing protocol: timed runs (0: no timing).
    #[arg(long, default_value_t = pixl_eval::DEFAULT_RUNS)]
    pub runs: usize,
}

fn parse_dtype(s: &str) -> anyhow::Result<DType> {
    match s {
        "f32" => Ok(DType::F32),
        "bf16" => Ok(DType::BF16),
        _ => anyhow::bail!("--dtype {s:?}: expected f32 or bf16"),
    }
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    let mut inputs: Vec<&std::path::Path> = Vec::new();
    inputs.extend(args.pairs.as_deref());
    inputs.extend(args.weights.iter().map(PathBuf::as_path));
    inputs.extend(args.lpips.as_deref());
    let labels = weight_labels(&args.weights, args.int8)?;
    let mut writes = vec!["results.md", "results.json", "per_pair.csv"];
    if let Some(sheet) = &args.sheet {
        if pixl_core::io::extension(sheet) != "png" {
            anyhow::bail!(
                "--sheet {}: the contact sheet is a PNG; give a file name ending in .png",
                sheet.display()
            );
        }
        if in_folder(sheet, &args.out) {
            // Checked with the output folder, which may not exist yet.
            writes.extend(sheet.file_name().and_then(|n| n.to_str()));
        } else {
            pixl_core::output::check_output(sheet, &["png"], &inputs)?;
        }
    }
    pixl_core::output::check_output_dir(&args.out, true, &writes, &inputs)?;
    let split: Split = args.split.parse()?;
    let dataset = pixl_data::open(&args.dataset, split)?;
    let mut pairs = match &args.pairs {
        Some(path) => pixl_eval::read_pairs(path, dataset.as_ref())?,
        None => pixl_eval::default_pairs(dataset.as_ref()),
    };
    if let Some(n) = args.limit {
        pairs.truncate(n);
    }
    let cases = if args.no_response {
        None
    } else {
        response_cases(&pairs, args.ct == "coarse")
    };
    if args.ct == "coarse" {
        for p in &mut pairs {
            let path = pixl_data::coarse_ct_path(&p.source.image, &p.target.image);
            if !path.is_file() {
                anyhow::bail!(
                    "--ct coarse: {} is missing (pair {} → {} of scene {}); make the set with `pixl synth --coarse` \
                     (it writes the pairs i → i+1 of every scene)",
                    path.display(),
                    p.source_name(),
                    p.target_name(),
                    p.scene
                );
            }
            p.target.intrinsics = Some(path);
        }
    }
    let device = crate::device::parse_device(&args.device)?;
    let dtype = parse_dtype(&args.dtype)?;

    let mut methods: Vec<Box<dyn Method>> = Vec::new();
    for (w, label) in args.weights.iter().zip(labels) {
        let (_cfg, mut model) = pixl_model::checkpoint::load(w, &device, dtype)?;
        if args.int8 {
            crate::device::check_int8(&device, dtype)?;
            if model.quantize_int8()? == 0 {
                anyhow::bail!("--int8: no layer quantized (this CPU has no AVX-512 VNNI, or every layer is narrower than {} inputs)", pixl_nn::linear::INT8_MIN_INPUTS);
            }
        }
        methods.push(Box::new(ModelMethod {
            label,
            model,
            device: device.clone(),
            max_side: args.max_side.map(|m| m as usize),
        }));
    }
    methods.extend(pixl_eval::parse_baselines(&args.baselines)?);
    let lpips = match &args.lpips {
        Some(p) => Some(Lpips::load(p, &device)?),
        None => None,
    };
    let opts = EvalOptions {
        scale_correction: !args.no_scale_correction,
        warmups: args.warmups,
        runs: args.runs,
        sheet_pairs: if args.sheet.is_some() { args.sheet_pairs } else { 0 },
    };

    let pb = ctx.progress(pairs.len() as u64, "eval");
    let label = if args.ct == "coarse" {
        let albedo = args
            .dataset
            .strip_prefix("synth:")
            .and_then(|root| pixl_data::folder::synth_coarse_albedo(std::path::Path::new(root)));
        let texture = match albedo {
            Some(pixl_data::CoarseAlbedo::Diffcol) => " textured with the source's DiffCol pass",
            Some(pixl_data::CoarseAlbedo::Photo) => " textured with the source image",
            Some(pixl_data::CoarseAlbedo::Estimated) => " textured with an estimated-style albedo",
            None => "",
        };
        format!("{} (C_T from coarse reconstructions{texture})", args.dataset)
    } else {
        args.dataset.clone()
    };
    let mut report = pixl_eval::run_eval(&label, &pairs, &methods, lpips.as_ref(), &opts, |i| {
        pb.set_position(i as u64)
    })?;
    pb.finish_and_clear();
    match &cases {
        Some(cases) => {
            let pb = ctx.progress(cases.len() as u64, "light response");
            report.response = pixl_eval::run_response(cases, &methods, |i| pb.set_position(i as u64))?;
            pb.finish_and_clear();
            report.response_renders = Some(if args.ct == "coarse" {
                "the coarse scene path-traced under each lighting".into()
            } else {
                "the data set's own images".into()
            });
        }
        _ if !args.no_response => {
            tracing::info!(
                "light response not computed: some pair lacks the C_T or render it needs (see --no-response)"
            )
        }
        _ => {}
    }
    if let Some(sheet) = &args.sheet {
        let image = pixl_eval::contact_sheet(&report.sheet_rows)?;
        // The sheet may go into --out, which write_reports would only create next.
        std::fs::create_dir_all(&args.out)
            .map_err(|e| anyhow::anyhow!("creating the output folder {}: {e}", args.out.display()))?;
        pixl_core::io::write_png(sheet, &image, pixl_core::io::PngDepth::Eight)?;
        report.sheet = Some(sheet.display().to_string());
    }
    pixl_eval::write_reports(&report, &args.out)?;

    if args.json {
        // The summary rows as JSON, with the same "inf" convention as results.json.
        let mut summary = serde_json::json!({
            "dataset": report.dataset,
            "pairs": report.pairs,
            "scale_correction": report.scale_correction,
            "lpips_net": report.lpips_net,
            "methods": report.methods,
            "response": report.response,
        });
        if let Some(sheet) = &report.sheet {
            summary["sheet"] = sheet.as_str().into();
            summary["sheet_columns"] = report.sheet_columns.clone().into();
        }
        ctx.print_json(&summary)?;
    } else {
        ctx.say(pixl_eval::report::markdown(&report));
        for m in &report.methods {
            if let Some(t) = &m.timing {
                ctx.say(format!("time {}: {} on {}", m.method, t.describe(), m.device));
            }
        }
        ctx.say(format!(
            "wrote {}/results.md, results.json, per_pair.csv",
            args.out.display()
        ));
        if let Some(sheet) = &report.sheet {
            ctx.say(format!(
                "wrote {sheet} ({} pairs; columns: {})",
                report.sheet_pairs,
                report.sheet_columns.join(" | ")
            ));
        }
    }
    Ok(())
}

/// The row label of each --weights file: "Ours" for a single one, "Ours (<file stem>)" for
/// several (", int8" added inside the parentheses with --int8). Two files of one stem would get
/// one label, so that is an error.
fn weight_labels(weights: &[PathBuf], int8: bool) -> anyhow::Result<Vec<String>> {
    if let [_] = weights {
        return Ok(vec![if int8 { "Ours (int8)" } else { "Ours" }.into()]);
    }
    let stem = |w: &PathBuf| {
        w.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let mut labels = Vec::with_capacity(weights.len());
    for (k, w) in weights.iter().enumerate() {
        let name = stem(w);
        if let Some(other) = weights[..k].iter().find(|o| stem(o) == name) {
            anyhow::bail!(
                "--weights {} and {} have the same file stem {name:?}, which names their rows in the \
                 tables (\"Ours ({name})\"); copy or link one of them under another name",
                other.display(),
                w.display()
            );
        }
        labels.push(if int8 {
            format!("Ours ({name}, int8)")
        } else {
            format!("Ours ({name})")
        });
    }
    Ok(labels)
}

/// Whether `file` lies directly in the folder `dir` (compared as written, or as files when both
/// exist).
fn in_folder(file: &Path, dir: &Path) -> bool {
    let parent = pixl_core::output::parent_dir(file);
    parent == dir || pixl_core::output::same_file(&parent, dir)
}

/// The light-response cases of `pairs` (see `--no-response`), or `None` when a file is missing.
fn response_cases(pairs: &[pixl_eval::Pair], coarse: bool) -> Option<Vec<pixl_eval::ResponseCase>> {
    let own_ct = |e: &pixl_data::ImageEntry| {
        e.intrinsics
            .clone()
            .unwrap_or_else(|| pixl_data::ct_cache_path(&e.image))
    };
    let cases: Vec<pixl_eval::ResponseCase> = pairs
        .iter()
        .map(|p| {
            let (src, tgt) = (&p.source.image, &p.target.image);
            let (cts, renders) = if coarse {
                (
                    [pixl_data::coarse_ct_path(src, src), pixl_data::coarse_ct_path(src, tgt)],
                    [
                        pixl_data::coarse_render_path(src, src),
                        pixl_data::coarse_render_path(src, tgt),
                    ],
                )
            } else {
                ([own_ct(&p.source), own_ct(&p.target)], [src.clone(), tgt.clone()])
            };
            pixl_eval::ResponseCase {
                scene: p.scene.clone(),
                source: src.clone(),
                cts,
                renders,
            }
        })
        .collect();
    let complete = cases
        .iter()
        .all(|c| c.cts.iter().chain(&c.renders).all(|f| f.is_file()));
    (complete && !cases.is_empty()).then_some(cases)
}
