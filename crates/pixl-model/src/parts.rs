//! Splitting a weights file into parts of bounded size, and joining the parts back into one file.
//!
//! A GPU machine hands back files of at most 16 MiB, far less than a `small` or `paper`
//! checkpoint; [`split`] cuts a pixl weights file (the format of [`crate::checkpoint`]) into parts
//! that each fit, optionally converting every tensor to f16 or bf16 first, and [`join`] puts the
//! parts back together.
//!
//! - **Parts** are safetensors files named `<stem>-00001-of-0000N.safetensors` (Hugging Face's
//!   sharding names) in the output folder. Tensors go into parts whole, in the order the file
//!   stores them (safetensors' order: by dtype, then by name; one dtype in a pixl file, so by
//!   name), greedily: a part takes the next tensor as long as its *whole file* (8-byte length,
//!   JSON header, data) stays within the limit. A tensor that does not fit in a part of its own
//!   is an error naming it and the size it needs.
//! - **Part metadata** is the source's, in the source's key order (with `dtype` updated when
//!   converting), followed by `part_index` and `part_count` (5 digits, as in the names, so a
//!   header's length does not depend on how many parts there are) and `parts_id`: 16 hex digits
//!   of an FNV-1a hash of that metadata and of every tensor's name, dtype, shape and bytes, and
//!   of the part count. Parts of different splits (another file, dtype or limit) therefore never
//!   pass for one set, and a part changed in transit fails the hash. A part alone is not a
//!   loadable checkpoint: its tensors are a subset.
//! - [`join`] takes the parts in any order, or one part, whose siblings it then finds beside it by
//!   their names. It checks that they form one complete set (one `parts_id` and count, indices
//!   `1..=N` once each, the same metadata, no tensor twice), that the merged tensors are exactly
//!   what the stored config asks for, and that they hash to `parts_id`; then it writes one file
//!   with the source's metadata (the part keys removed).
//! - **Byte identity.** Without a dtype conversion, `join(split(f))` is byte for byte `f` for any
//!   file written by `safetensors::serialize`, as [`crate::save`] writes them: the header is the
//!   same compact JSON (`__metadata__` first, then one entry per tensor in the data's order),
//!   padded with spaces to a multiple of 8, and the data are the source's bytes. safetensors takes
//!   the metadata as a `HashMap`, so its key order changes from one save to the next; the parts
//!   keep the order found in the source's header and the joined file gets it back.
//! - **Writes** are atomic ([`pixl_core::io::atomic_write`]). An input is never overwritten (not
//!   the file being split, not a part being joined); other existing files only with
//!   [`Overwrite::Allow`]. For a split that means any part of the same stem already in the
//!   folder, of this split's count or another: with `Allow` the new set replaces those of the same
//!   names and the others are removed, so the folder holds one set. A split writes all its parts
//!   under hidden staging names first and renames them only once every one is complete: a split
//!   that fails or is interrupted leaves an earlier set whole, and removes what it created (the
//!   folder too). A set mixed all the same (a failure among the renames) is caught by [`join`].
//! - **Memory**: the source (split) or all parts (join) are read whole, plus the converted copy
//!   when converting.
use crate::checkpoint::{self, CheckpointError};
use candle_core::safetensors::Load;
use candle_core::{DType, Device};
use safetensors::tensor::{Dtype as StDtype, SafeTensors, TensorInfo, TensorView};
use serde::ser::SerializeMap;
use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// The default largest part, in bytes (16 MiB: what a GPU machine returns per file).
pub const DEFAULT_MAX_PART_BYTES: u64 = 16 * 1024 * 1024;
/// Metadata key: the part's number, `00001` to `part_count`.
pub const PART_INDEX: &str = "part_index";
/// Metadata key: how many parts the set has.
pub const PART_COUNT: &str = "part_count";
/// Metadata key: the hash shared by all parts of one split.
pub const PARTS_ID: &str = "parts_id";
/// Digits of part numbers in names and metadata; also the most parts a split makes (99 999).
const NUMBER_WIDTH: usize = 5;
/// The most parts one split makes.
pub const MAX_PARTS: usize = 99_999;
const EXT: &str = "safetensors";

/// Splitting and joining errors. Each names the file (and the tensor or part) it is about.
#[derive(Debug, thiserror::Error)]
pub enum PartsError {
    /// Reading, validating or writing a weights file.
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("cannot convert weights to {dtype:?}: only F32, F16 and BF16 are written")]
    UnsupportedDtype { dtype: DType },
    #[error(
        "{path}: tensor `{name}` ({data} bytes) needs a part of {needs} bytes on its own, over the limit of \
         {limit} bytes; raise the limit or convert to a smaller dtype"
    )]
    TensorTooLarge {
        path: PathBuf,
        name: String,
        data: u64,
        needs: u64,
        limit: u64,
    },
    #[error("{path}: {count} parts of at most {limit} bytes would be needed, more than {max}; raise the limit")]
    TooManyParts {
        path: PathBuf,
        count: usize,
        limit: u64,
        max: usize,
    },
    #[error("{path}: the output is the input {input}; write somewhere else")]
    OutputIsInput { path: PathBuf, input: PathBuf },
    #[error("{path}: already exists; it is replaced only on request (--force)")]
    Exists { path: PathBuf },
    #[error(
        "{dir}: already holds {count} parts of a split of `{stem}` (first: {first}); they are replaced only on \
         request (--force), or choose another folder"
    )]
    PartsExist {
        dir: PathBuf,
        count: usize,
        stem: String,
        first: PathBuf,
    },
    #[error("no parts given")]
    NoParts,
    #[error("{path}: not a part of split weights: {reason}")]
    NotAPart { path: PathBuf, reason: String },
    #[error("{path}: belongs to another split (parts_id {found}, {found_count} parts) than {first} (parts_id {expected}, {expected_count} parts)")]
    MixedSplits {
        path: PathBuf,
        found: String,
        found_count: usize,
        first: PathBuf,
        expected: String,
        expected_count: usize,
    },
    #[error("{path}: its metadata differs from that of {first}, a part of the same split")]
    MetadataDiffers { path: PathBuf, first: PathBuf },
    #[error("{path}: part {index} of {count} is missing (a part's siblings are looked for beside it, by name)")]
    MissingPartFile { path: PathBuf, index: usize, count: usize },
    #[error("part {index} of {count} is missing ({given} parts given; give all {count}, or one of them to find the others beside it)")]
    MissingPart { index: usize, count: usize, given: usize },
    #[error("{a} and {b} are both part {index} of {count}")]
    DuplicatePart {
        a: PathBuf,
        b: PathBuf,
        index: usize,
        count: usize,
    },
    #[error("tensor `{name}` is in both {a} and {b}")]
    DuplicateTensor { name: String, a: PathBuf, b: PathBuf },
    #[error(
        "{first}: the joined tensors and metadata hash to {computed}, not to the parts' parts_id {stored}: \
         a part is corrupt or was changed"
    )]
    HashMismatch {
        first: PathBuf,
        stored: String,
        computed: String,
    },
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

pub type Result<T, E = PartsError> = std::result::Result<T, E>;

/// Whether existing files may be replaced (inputs never are).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Overwrite {
    Refuse,
    Allow,
}

/// What [`split`] does besides cutting.
#[derive(Clone, Debug)]
pub struct SplitOptions {
    /// Convert every tensor to this dtype (F32, F16 or BF16); `None` keeps the file's.
    pub dtype: Option<DType>,
    /// The largest part file, in bytes, header included.
    pub max_part_bytes: u64,
    /// Whether part files already in the output folder may be replaced.
    pub overwrite: Overwrite,
}

impl Default for SplitOptions {
    fn default() -> Self {
        SplitOptions {
            dtype: None,
            max_part_bytes: DEFAULT_MAX_PART_BYTES,
            overwrite: Overwrite::Refuse,
        }
    }
}

/// One part written by [`split`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PartFile {
    pub path: PathBuf,
    /// The file's size.
    pub bytes: u64,
    /// How many tensors it holds.
    pub tensors: usize,
}

/// What [`split`] wrote.
#[derive(Clone, Debug)]
pub struct SplitSummary {
    /// The parts, in order (index 1 first).
    pub parts: Vec<PartFile>,
    /// The dtype of the source file's tensors.
    pub source_dtype: DType,
    /// The dtype of the parts' tensors.
    pub dtype: DType,
    /// The `parts_id` of every part.
    pub parts_id: String,
    /// Parts of an earlier split of the same name in the folder that were removed (only with
    /// [`Overwrite::Allow`]; parts of the same names were replaced).
    pub removed: Vec<PathBuf>,
}

/// What [`join`] wrote.
#[derive(Clone, Debug)]
pub struct JoinSummary {
    pub output: PathBuf,
    /// The file's size.
    pub bytes: u64,
    pub tensors: usize,
    pub dtype: DType,
    /// The parts read, in index order.
    pub parts: Vec<PathBuf>,
    pub parts_id: String,
}

/// One tensor as it will be written: name, safetensors dtype, shape and bytes (borrowed from the
/// file read, or owned after a conversion).
struct Entry<'a> {
    name: String,
    dtype: StDtype,
    shape: Vec<usize>,
    data: Cow<'a, [u8]>,
}

/// Splits the weights file `input` into parts of at most `opts.max_part_bytes` bytes in
/// `out_dir` (created if missing); see the module docs for names, metadata and refusals.
pub fn split(input: &Path, out_dir: &Path, opts: &SplitOptions) -> Result<SplitSummary> {
    if let Some(dtype) = opts.dtype {
        check_dtype(dtype)?;
    }
    let bytes = checkpoint::read_bytes(input)?;
    let parsed = checkpoint::parse(input, &bytes, None)?;
    let source_meta = ordered_metadata(input, &bytes)?;
    let mut views = parsed.tensors.tensors();
    views.sort_by(|(a, va), (b, vb)| vb.dtype().cmp(&va.dtype()).then_with(|| a.cmp(b)));
    // `parse` checked every tensor against the metadata's dtype, so the first one speaks for all.
    let source_dtype = match views.first() {
        Some((_, v)) => DType::try_from(v.dtype())?,
        None => DType::F32,
    };
    let dtype = opts.dtype.unwrap_or(source_dtype);
    let mut meta: Vec<(String, String)> = source_meta.into_iter().filter(|(k, _)| !is_part_key(k)).collect();
    if dtype != source_dtype {
        let name = dtype_name(dtype);
        match meta.iter_mut().find(|(k, _)| k == "dtype") {
            Some((_, v)) => *v = name,
            None => meta.push(("dtype".into(), name)),
        }
    }

    // Plan with the sizes alone, so outputs are checked before any conversion work.
    let st_dtype = StDtype::from(dtype);
    let sizes: Vec<usize> = views
        .iter()
        .map(|(_, v)| v.shape().iter().product::<usize>() * dtype.size_in_bytes())
        .collect();
    let placeholder = with_part_keys(&meta, 1, 1, &"0".repeat(16));
    let base = header_json(input, &placeholder, &[])?.len();
    let planned: Vec<(&str, &[usize], usize)> = views
        .iter()
        .zip(&sizes)
        .map(|((n, v), &s)| (n.as_str(), v.shape(), s))
        .collect();
    let ranges = plan_parts(input, &planned, st_dtype, base, opts.max_part_bytes)?;
    let count = ranges.len();
    if count > MAX_PARTS {
        return Err(PartsError::TooManyParts {
            path: input.to_owned(),
            count,
            limit: opts.max_part_bytes,
            max: MAX_PARTS,
        });
    }
    let stem = input
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "weights".into());
    let paths: Vec<PathBuf> = (1..=count).map(|i| out_dir.join(part_name(&stem, i, count))).collect();
    for path in &paths {
        if pixl_core::output::same_file(path, input) {
            return Err(PartsError::OutputIsInput {
                path: path.clone(),
                input: input.to_owned(),
            });
        }
    }
    let existing = existing_parts(out_dir, &stem)?;
    if let (Overwrite::Refuse, Some(first)) = (opts.overwrite, existing.first()) {
        return Err(PartsError::PartsExist {
            dir: out_dir.to_owned(),
            count: existing.len(),
            stem,
            first: first.clone(),
        });
    }

    let entries = views
        .iter()
        .map(|(name, view)| {
            Ok(Entry {
                name: name.clone(),
                dtype: st_dtype,
                shape: view.shape().to_vec(),
                data: converted(view, dtype)?,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let parts_id = parts_id(&meta, &entries, count);

    let mut made = pixl_core::output::Provisional::new();
    made.create_dir_all(out_dir).map_err(|source| CheckpointError::Write {
        path: out_dir.to_owned(),
        source,
    })?;
    // Every part is first written under a hidden staging name and renamed only once all are
    // complete, so a failed or interrupted split (a GPU call cut short while it exports) leaves
    // the folder's earlier set whole rather than mixed with a half-written new one.
    let mut staged = Vec::with_capacity(count);
    for (i, (range, path)) in ranges.into_iter().zip(paths).enumerate() {
        let part_meta = with_part_keys(&meta, i + 1, count, &parts_id);
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let tmp = path.with_file_name(format!(".{name}.staged-{}", std::process::id()));
        made.add_new_file(&tmp);
        let bytes = write_file(&tmp, &part_meta, &entries[range.clone()])?;
        debug_assert!(bytes <= opts.max_part_bytes, "{}: {bytes} bytes", path.display());
        staged.push((
            tmp,
            PartFile {
                path,
                bytes,
                tensors: range.len(),
            },
        ));
    }
    let mut parts = Vec::with_capacity(count);
    for (tmp, part) in staged {
        made.add_new_file(&part.path);
        std::fs::rename(&tmp, &part.path).map_err(|source| CheckpointError::Io {
            path: part.path.clone(),
            source,
        })?;
        parts.push(part);
    }
    made.keep();
    // Parts of an earlier split of the same name that the new set did not replace would mix
    // with it in `join parts/*.safetensors`: with overwriting allowed, they go.
    let mut removed = Vec::new();
    for old in existing {
        if !parts.iter().any(|p| p.path == old) {
            std::fs::remove_file(&old).map_err(|source| CheckpointError::Io {
                path: old.clone(),
                source,
            })?;
            removed.push(old);
        }
    }
    Ok(SplitSummary {
        parts,
        removed,
        source_dtype,
        dtype,
        parts_id,
    })
}

/// A part read from disk, with its part keys parsed.
struct PartBytes {
    path: PathBuf,
    bytes: Vec<u8>,
    index: usize,
    count: usize,
    id: String,
    /// The metadata without the part keys, in the file's order.
    meta: Vec<(String, String)>,
}

/// Joins the parts of one split into `output`; see the module docs for the checks. `parts` may
/// be in any order; a single path that follows the part naming stands for its whole set.
pub fn join(parts: &[PathBuf], output: &Path, overwrite: Overwrite) -> Result<JoinSummary> {
    let paths = match parts {
        [] => return Err(PartsError::NoParts),
        [one] => siblings(one)?,
        many => many.to_vec(),
    };
    for path in &paths {
        if pixl_core::output::same_file(output, path) {
            return Err(PartsError::OutputIsInput {
                path: output.to_owned(),
                input: path.clone(),
            });
        }
    }
    if overwrite == Overwrite::Refuse && std::fs::symlink_metadata(output).is_ok() {
        return Err(PartsError::Exists {
            path: output.to_owned(),
        });
    }

    let mut read = paths.iter().map(|p| read_part(p)).collect::<Result<Vec<_>>>()?;
    let first = &read[0];
    for part in &read[1..] {
        if part.id != first.id || part.count != first.count {
            return Err(PartsError::MixedSplits {
                path: part.path.clone(),
                found: part.id.clone(),
                found_count: part.count,
                first: first.path.clone(),
                expected: first.id.clone(),
                expected_count: first.count,
            });
        }
        if part.meta != first.meta {
            return Err(PartsError::MetadataDiffers {
                path: part.path.clone(),
                first: first.path.clone(),
            });
        }
    }
    read.sort_by_key(|p| p.index);
    let count = read[0].count;
    for pair in read.windows(2) {
        if pair[0].index == pair[1].index {
            return Err(PartsError::DuplicatePart {
                a: pair[0].path.clone(),
                b: pair[1].path.clone(),
                index: pair[0].index,
                count,
            });
        }
    }
    // Indices are distinct and in 1..=count (read_part checks the range): any gap is a missing part.
    if let Some(index) = (1..=count).find(|i| read.get(i - 1).map(|p| p.index) != Some(*i)) {
        return Err(PartsError::MissingPart {
            index,
            count,
            given: read.len(),
        });
    }

    let first_path = read[0].path.clone();
    let mut entries: Vec<Entry> = Vec::new();
    let mut owner: HashMap<String, usize> = HashMap::new();
    for (k, part) in read.iter().enumerate() {
        let tensors = SafeTensors::deserialize(&part.bytes).map_err(|e| CheckpointError::NotSafetensors {
            path: part.path.clone(),
            msg: e.to_string(),
        })?;
        for (name, view) in tensors.tensors() {
            if let Some(&j) = owner.get(&name) {
                return Err(PartsError::DuplicateTensor {
                    name,
                    a: read[j].path.clone(),
                    b: part.path.clone(),
                });
            }
            owner.insert(name.clone(), k);
            entries.push(Entry {
                name,
                dtype: view.dtype(),
                shape: view.shape().to_vec(),
                data: Cow::Borrowed(view.data()),
            });
        }
    }
    entries.sort_by(|a, b| b.dtype.cmp(&a.dtype).then_with(|| a.name.cmp(&b.name)));

    // The merged tensors must be a whole checkpoint, as `checkpoint::load` will want it.
    let meta = read[0].meta.clone();
    let meta_map: HashMap<String, String> = meta.iter().cloned().collect();
    let (cfg, dtype_name) = checkpoint::config_from_metadata(&first_path, Some(&meta_map))?;
    let expected = checkpoint::param_shapes(&cfg)?;
    let found: BTreeMap<String, (Vec<usize>, String)> = entries
        .iter()
        .map(|e| (e.name.clone(), (e.shape.clone(), format!("{:?}", e.dtype))))
        .collect();
    checkpoint::check_against(&first_path, &expected, &found, &dtype_name)?;
    let computed = parts_id(&meta, &entries, count);
    if computed != read[0].id {
        return Err(PartsError::HashMismatch {
            first: first_path,
            stored: read[0].id.clone(),
            computed,
        });
    }

    let bytes = write_file(output, &meta, &entries)?;
    let dtype = match entries.first() {
        Some(e) => DType::try_from(e.dtype)?,
        None => DType::F32,
    };
    Ok(JoinSummary {
        output: output.to_owned(),
        bytes,
        tensors: entries.len(),
        dtype,
        parts: read.iter().map(|p| p.path.clone()).collect(),
        parts_id: computed,
    })
}

/// The name of part `index` of `count`: `<stem>-00001-of-00004.safetensors`.
pub fn part_name(stem: &str, index: usize, count: usize) -> String {
    format!("{stem}-{index:0w$}-of-{count:0w$}.{EXT}", w = NUMBER_WIDTH)
}

/// A part name's stem, index and count, and the widths of its two numbers
/// (`W-00002-of-00004.safetensors` → `("W", 2, 4)`); `None` for other names.
fn parse_part_name(name: &str) -> Option<(&str, usize, usize, usize, usize)> {
    let base = name.strip_suffix(&format!(".{EXT}"))?;
    let (left, count) = base.rsplit_once("-of-")?;
    let (stem, index) = left.rsplit_once('-')?;
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if stem.is_empty() || !digits(index) || !digits(count) {
        return None;
    }
    Some((stem, index.parse().ok()?, count.parse().ok()?, index.len(), count.len()))
}

/// The whole set a single path stands for: its siblings by name when it follows the part
/// naming, else the path alone (then it must be a set of one).
fn siblings(path: &Path) -> Result<Vec<PathBuf>> {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
    let Some((stem, _, count, wi, wc)) = parse_part_name(name) else {
        return Ok(vec![path.to_owned()]);
    };
    let mut out = Vec::with_capacity(count);
    for index in 1..=count {
        let sibling = path.with_file_name(format!("{stem}-{index:0wi$}-of-{count:0wc$}.{EXT}"));
        if !sibling.exists() {
            return Err(PartsError::MissingPartFile {
                path: sibling,
                index,
                count,
            });
        }
        out.push(sibling);
    }
    Ok(out)
}

/// The files in `dir` named as parts of `stem` (of any count), sorted; none if `dir` is missing.
fn existing_parts(dir: &Path, stem: &str) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        return Ok(Vec::new());
    }
    let io = |source| CheckpointError::Io {
        path: dir.to_owned(),
        source,
    };
    let mut found = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let entry = entry.map_err(io)?;
        let name = entry.file_name();
        if parse_part_name(&name.to_string_lossy()).is_some_and(|(s, ..)| s == stem) {
            found.push(entry.path());
        }
    }
    found.sort();
    Ok(found)
}

fn read_part(path: &Path) -> Result<PartBytes> {
    let bytes = checkpoint::read_bytes(path)?;
    SafeTensors::deserialize(&bytes).map_err(|e| CheckpointError::NotSafetensors {
        path: path.to_owned(),
        msg: e.to_string(),
    })?;
    let all = ordered_metadata(path, &bytes)?;
    let not_part = |reason: String| PartsError::NotAPart {
        path: path.to_owned(),
        reason,
    };
    let get = |key: &str| {
        all.iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
            .ok_or_else(|| not_part(format!("no `{key}` in its metadata")))
    };
    let number = |key: &str| -> Result<usize> {
        let v = get(key)?;
        v.parse::<usize>()
            .map_err(|_| not_part(format!("`{key}` is {v:?}, not a whole number")))
    };
    let index = number(PART_INDEX)?;
    let count = number(PART_COUNT)?;
    if count == 0 || index == 0 || index > count {
        return Err(not_part(format!("part {index} of {count} is not a valid part number")));
    }
    let id = get(PARTS_ID)?.to_string();
    let meta = all.iter().filter(|(k, _)| !is_part_key(k)).cloned().collect();
    Ok(PartBytes {
        path: path.to_owned(),
        bytes,
        index,
        count,
        id,
        meta,
    })
}

fn is_part_key(key: &str) -> bool {
    [PART_INDEX, PART_COUNT, PARTS_ID].contains(&key)
}

fn with_part_keys(meta: &[(String, String)], index: usize, count: usize, id: &str) -> Vec<(String, String)> {
    let mut out = meta.to_vec();
    out.push((PART_INDEX.into(), format!("{index:0w$}", w = NUMBER_WIDTH)));
    out.push((PART_COUNT.into(), format!("{count:0w$}", w = NUMBER_WIDTH)));
    out.push((PARTS_ID.into(), id.to_string()));
    out
}

fn check_dtype(dtype: DType) -> Result<()> {
    match dtype {
        DType::F32 | DType::F16 | DType::BF16 => Ok(()),
        other => Err(PartsError::UnsupportedDtype { dtype: other }),
    }
}

/// The metadata's name of a dtype (`F32`, `F16`, `BF16`), as safetensors spells it.
fn dtype_name(dtype: DType) -> String {
    format!("{:?}", StDtype::from(dtype))
}

/// A tensor's bytes in `to`: the file's own bytes when it already is, else converted with
/// candle's `to_dtype` (round to nearest even), little-endian.
fn converted<'a>(view: &TensorView<'a>, to: DType) -> Result<Cow<'a, [u8]>> {
    if DType::try_from(view.dtype())? == to {
        return Ok(Cow::Borrowed(view.data()));
    }
    let t = view.load(&Device::Cpu)?.to_dtype(to)?.flatten_all()?;
    let bytes: Vec<u8> = match to {
        DType::F32 => t.to_vec1::<f32>()?.iter().flat_map(|v| v.to_le_bytes()).collect(),
        DType::F16 => t.to_vec1::<half::f16>()?.iter().flat_map(|v| v.to_le_bytes()).collect(),
        DType::BF16 => t
            .to_vec1::<half::bf16>()?
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect(),
        other => return Err(PartsError::UnsupportedDtype { dtype: other }),
    };
    Ok(Cow::Owned(bytes))
}

/// Greedy partition of tensors `(name, shape, bytes)`, in file order, into ranges whose part
/// files stay within `limit` bytes. `base` is the length of the header JSON with no tensors
/// (the metadata alone); each tensor adds `,"name":{"dtype":…,"shape":[…],"data_offsets":[a,b]}`.
fn plan_parts(
    path: &Path,
    tensors: &[(&str, &[usize], usize)],
    dtype: StDtype,
    base: usize,
    limit: u64,
) -> Result<Vec<Range<usize>>> {
    let file_len = |header: usize, data: usize| (8 + header.next_multiple_of(8) + data) as u64;
    let mut ranges = Vec::new();
    let (mut start, mut header, mut offset) = (0, base, 0);
    let mut i = 0;
    while i < tensors.len() {
        let (name, shape, size) = tensors[i];
        let entry = entry_json_len(path, name, dtype, shape, offset, offset + size)?;
        let needs = file_len(header + entry, offset + size);
        if needs <= limit {
            header += entry;
            offset += size;
            i += 1;
        } else if i == start {
            return Err(PartsError::TensorTooLarge {
                path: path.to_owned(),
                name: name.to_string(),
                data: size as u64,
                needs,
                limit,
            });
        } else {
            ranges.push(start..i);
            (start, header, offset) = (i, base, 0);
        }
    }
    if start < tensors.len() || ranges.is_empty() {
        ranges.push(start..tensors.len());
    }
    Ok(ranges)
}

fn encode_error(path: &Path, e: serde_json::Error) -> PartsError {
    PartsError::Checkpoint(CheckpointError::NotSafetensors {
        path: path.to_owned(),
        msg: format!("cannot encode the header: {e}"),
    })
}

/// Length of one tensor's header entry, with the comma before it.
fn entry_json_len(path: &Path, name: &str, dtype: StDtype, shape: &[usize], start: usize, end: usize) -> Result<usize> {
    let info = TensorInfo {
        dtype,
        shape: shape.to_vec(),
        data_offsets: (start, end),
    };
    let key = serde_json::to_string(name).map_err(|e| encode_error(path, e))?;
    let value = serde_json::to_string(&info).map_err(|e| encode_error(path, e))?;
    Ok(1 + key.len() + 1 + value.len())
}

/// The metadata as a JSON object, keys in the given order.
struct OrderedMeta<'a>(&'a [(String, String)]);

impl serde::Serialize for OrderedMeta<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        let mut map = s.serialize_map(Some(self.0.len()))?;
        for (k, v) in self.0 {
            map.serialize_entry(k, v)?;
        }
        map.end()
    }
}

/// A safetensors header: `__metadata__` first, then the tensors in the order given.
struct Header<'a> {
    meta: &'a [(String, String)],
    tensors: &'a [(&'a str, TensorInfo)],
}

impl serde::Serialize for Header<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        let mut map = s.serialize_map(Some(1 + self.tensors.len()))?;
        map.serialize_entry("__metadata__", &OrderedMeta(self.meta))?;
        for (name, info) in self.tensors {
            map.serialize_entry(name, info)?;
        }
        map.end()
    }
}

/// The header JSON (unpadded) of a file holding `entries` in the given order.
fn header_json(path: &Path, meta: &[(String, String)], entries: &[Entry]) -> Result<Vec<u8>> {
    let mut offset = 0;
    let infos: Vec<(&str, TensorInfo)> = entries
        .iter()
        .map(|e| {
            let info = TensorInfo {
                dtype: e.dtype,
                shape: e.shape.clone(),
                data_offsets: (offset, offset + e.data.len()),
            };
            offset += e.data.len();
            (e.name.as_str(), info)
        })
        .collect();
    serde_json::to_vec(&Header { meta, tensors: &infos }).map_err(|e| encode_error(path, e))
}

/// Writes `entries` (in safetensors' order: dtype descending, then name) with `meta` as one
/// safetensors file, atomically, as `safetensors::serialize` lays it out: the header's length
/// (u64, little-endian), the header padded with spaces to a multiple of 8, the data. Returns the
/// file's size.
fn write_file(path: &Path, meta: &[(String, String)], entries: &[Entry]) -> Result<u64> {
    debug_assert!(entries
        .windows(2)
        .all(|w| (std::cmp::Reverse(w[0].dtype), &w[0].name) < (std::cmp::Reverse(w[1].dtype), &w[1].name)));
    let mut header = header_json(path, meta, entries)?;
    header.resize(header.len().next_multiple_of(8), b' ');
    let data: usize = entries.iter().map(|e| e.data.len()).sum();
    pixl_core::io::atomic_write(path, |file| {
        let io = |e| pixl_core::CoreError::io(path, e);
        let mut out = std::io::BufWriter::new(file);
        out.write_all(&(header.len() as u64).to_le_bytes()).map_err(io)?;
        out.write_all(&header).map_err(io)?;
        for e in entries {
            out.write_all(&e.data).map_err(io)?;
        }
        out.flush().map_err(io)
    })
    .map_err(|source| CheckpointError::Write {
        path: path.to_owned(),
        source,
    })?;
    Ok((8 + header.len() + data) as u64)
}

/// The `__metadata__` of a safetensors file's header as key–value pairs in the order the file
/// stores them (safetensors' own reader gives a `HashMap`, which loses it).
fn ordered_metadata(path: &Path, bytes: &[u8]) -> Result<Vec<(String, String)>> {
    let bad = |msg: String| CheckpointError::NotSafetensors {
        path: path.to_owned(),
        msg,
    };
    let len = bytes
        .get(..8)
        .and_then(|b| <[u8; 8]>::try_from(b).ok())
        .map(u64::from_le_bytes)
        .ok_or_else(|| bad("shorter than the 8-byte header length".into()))?;
    let header = usize::try_from(len)
        .ok()
        .and_then(|n| n.checked_add(8))
        .and_then(|end| bytes.get(8..end))
        .ok_or_else(|| bad(format!("header of {len} bytes is truncated")))?;
    #[derive(serde::Deserialize)]
    struct HeaderMeta {
        #[serde(rename = "__metadata__", default)]
        metadata: Option<MetaPairs>,
    }
    let parsed: HeaderMeta = serde_json::from_slice(header).map_err(|e| bad(format!("header is not JSON: {e}")))?;
    let pairs = parsed.metadata.map(|m| m.0).unwrap_or_default();
    let mut seen = std::collections::HashSet::new();
    if let Some((k, _)) = pairs.iter().find(|(k, _)| !seen.insert(k.as_str())) {
        return Err(bad(format!("metadata key `{k}` appears twice")).into());
    }
    Ok(pairs)
}

/// A JSON object of strings read in document order.
struct MetaPairs(Vec<(String, String)>);

impl<'de> serde::Deserialize<'de> for MetaPairs {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        struct Pairs;
        impl<'de> serde::de::Visitor<'de> for Pairs {
            type Value = MetaPairs;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an object of strings")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> std::result::Result<MetaPairs, A::Error> {
                let mut out = Vec::new();
                while let Some(pair) = map.next_entry::<String, String>()? {
                    out.push(pair);
                }
                Ok(MetaPairs(out))
            }
        }
        d.deserialize_map(Pairs)
    }
}

/// 64-bit FNV-1a over length-prefixed fields.
struct Fnv(u64);

impl Fnv {
    fn field(&mut self, bytes: &[u8]) {
        for b in (bytes.len() as u64).to_le_bytes().iter().chain(bytes) {
            self.0 = (self.0 ^ *b as u64).wrapping_mul(0x0100_0000_01b3);
        }
    }
}

/// The `parts_id` of a split: a hash of the metadata (without the part keys), every tensor's
/// name, dtype, shape and bytes (in file order) and the part count, as 16 hex digits.
fn parts_id(meta: &[(String, String)], entries: &[Entry], count: usize) -> String {
    let mut h = Fnv(0xcbf2_9ce4_8422_2325);
    h.field(b"pixl-parts-1");
    for (k, v) in meta {
        h.field(k.as_bytes());
        h.field(v.as_bytes());
    }
    for e in entries {
        h.field(e.name.as_bytes());
        h.field(format!("{:?}", e.dtype).as_bytes());
        for d in &e.shape {
            h.field(&(*d as u64).to_le_bytes());
        }
        h.field(&e.data);
    }
    h.field(&(count as u64).to_le_bytes());
    format!("{:016x}", h.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn part_names_round_trip() {
        assert_eq!(part_name("W", 2, 4), "W-00002-of-00004.safetensors");
        assert_eq!(parse_part_name("W-00002-of-00004.safetensors"), Some(("W", 2, 4, 5, 5)));
        assert_eq!(
            parse_part_name("a-b-00001-of-00001.safetensors"),
            Some(("a-b", 1, 1, 5, 5))
        );
        assert_eq!(parse_part_name("W.safetensors"), None);
        assert_eq!(parse_part_name("W-x-of-00004.safetensors"), None);
        assert_eq!(parse_part_name("-00001-of-00002.safetensors"), None);
    }

    #[test]
    fn planned_sizes_are_the_written_sizes() {
        let dir = tempfile::tempdir().unwrap();
        let meta = vec![
            ("format".to_string(), "x".to_string()),
            ("config".to_string(), "{\"a\":\"b\"}".to_string()),
        ];
        let data: Vec<Vec<u8>> = (0..7).map(|i| vec![i as u8; 4 * (i * 37 + 3)]).collect();
        let entries: Vec<Entry> = data
            .iter()
            .enumerate()
            .map(|(i, d)| Entry {
                name: format!("t.{i}"),
                dtype: StDtype::F32,
                shape: vec![d.len() / 4],
                data: Cow::Borrowed(d),
            })
            .collect();
        let base = header_json(dir.path(), &meta, &[]).unwrap().len();
        let planned: Vec<(&str, &[usize], usize)> = entries
            .iter()
            .map(|e| (e.name.as_str(), e.shape.as_slice(), e.data.len()))
            .collect();
        for limit in [1100u64, 1500, 2500, 100_000] {
            let ranges = plan_parts(dir.path(), &planned, StDtype::F32, base, limit).unwrap();
            assert_eq!(ranges.iter().map(|r| r.len()).sum::<usize>(), entries.len());
            for (k, r) in ranges.iter().enumerate() {
                let path = dir.path().join(format!("p{limit}-{k}.safetensors"));
                let bytes = write_file(&path, &meta, &entries[r.clone()]).unwrap();
                assert_eq!(bytes, std::fs::metadata(&path).unwrap().len());
                assert!(bytes <= limit, "{bytes} > {limit}");
                // and the next tensor would not have fitted
                if r.end < entries.len() {
                    let probe = dir.path().join("probe.safetensors");
                    let more = write_file(&probe, &meta, &entries[r.start..r.end + 1]).unwrap();
                    assert!(more > limit, "part {k} could have taken one more tensor");
                }
            }
        }
    }
}
