//! The rename table between the official release's tensor names and ours, as data
//! (`names.toml` beside this file, compiled in; a replacement can be read from a file).
//!
//! A [`Pattern`] is a dotted name with `{x}` placeholders, each matching one or more characters
//! (dots included). A [`Rule`] pairs a pattern over our names with one over theirs, with the same
//! placeholders, so it maps both ways: [`NameTable::theirs`] (ours → theirs, used to load) and
//! [`NameTable::ours`] (theirs → ours, used to read a file's architecture and to report what it
//! holds). The first rule that matches wins. `[[ignore]]` patterns name tensors a file may hold
//! that the network never reads.
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The table compiled into the binary.
pub const BUILTIN: &str = include_str!("names.toml");

/// A name table or its conventions could not be read.
#[derive(Debug, thiserror::Error)]
pub enum NamesError {
    #[error("name table {origin}: {msg}")]
    Parse { origin: String, msg: String },
    #[error("name table {origin}: rule {index} (`{ours}` ↔ `{theirs}`): {msg}")]
    BadRule {
        origin: String,
        index: usize,
        ours: String,
        theirs: String,
        msg: String,
    },
}

/// What the gain channels of the final conv hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Gain {
    /// The whole gain `1 + g` (the loader subtracts 1 from those channels' bias).
    Whole,
    /// The residual `g`, as ours.
    Residual,
}

/// What the source image is before the network sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SourceNorm {
    /// sRGB values in `[0, 1]`, as ours.
    Srgb,
    /// `(x − mean) / std` with ImageNet's statistics (folded into the patch embedding at load).
    Imagenet,
}

/// The official checkpoint's input/output conventions.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Conventions {
    pub gain: Gain,
    pub source_norm: SourceNorm,
    /// Inputs are edge-padded to a multiple of this.
    pub pad_multiple: usize,
}

#[derive(Clone, Debug, PartialEq, Eq)]
enum Piece {
    Lit(String),
    Var(String),
}

/// A dotted-name pattern with `{x}` placeholders.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Pattern {
    text: String,
    pieces: Vec<Piece>,
}

impl Pattern {
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut pieces = Vec::new();
        let mut rest = text;
        while let Some(open) = rest.find('{') {
            if open > 0 {
                pieces.push(Piece::Lit(rest[..open].to_string()));
            }
            let close = rest[open..]
                .find('}')
                .map(|c| open + c)
                .ok_or_else(|| format!("`{text}`: unclosed `{{`"))?;
            let var = &rest[open + 1..close];
            if var.is_empty() || !var.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                return Err(format!("`{text}`: placeholder `{{{var}}}` must be a plain name"));
            }
            if matches!(pieces.last(), Some(Piece::Var(_))) {
                return Err(format!("`{text}`: two placeholders in a row are ambiguous"));
            }
            pieces.push(Piece::Var(var.to_string()));
            rest = &rest[close + 1..];
        }
        if rest.contains('}') {
            return Err(format!("`{text}`: stray `}}`"));
        }
        if !rest.is_empty() {
            pieces.push(Piece::Lit(rest.to_string()));
        }
        if pieces.is_empty() {
            return Err("empty pattern".into());
        }
        Ok(Self {
            text: text.to_string(),
            pieces,
        })
    }

    pub fn as_str(&self) -> &str {
        &self.text
    }

    fn vars(&self) -> Vec<&str> {
        let mut v: Vec<&str> = self
            .pieces
            .iter()
            .filter_map(|p| match p {
                Piece::Var(v) => Some(v.as_str()),
                Piece::Lit(_) => None,
            })
            .collect();
        v.sort_unstable();
        v
    }

    /// The placeholders' values if `name` matches (each one or more characters).
    pub fn matches(&self, name: &str) -> Option<BTreeMap<String, String>> {
        let mut out = BTreeMap::new();
        match_from(&self.pieces, name, &mut out).then_some(out)
    }

    /// The name this pattern gives for `values`.
    pub fn fill(&self, values: &BTreeMap<String, String>) -> Option<String> {
        let mut s = String::new();
        for p in &self.pieces {
            match p {
                Piece::Lit(l) => s.push_str(l),
                Piece::Var(v) => s.push_str(values.get(v)?),
            }
        }
        Some(s)
    }
}

fn match_from(pieces: &[Piece], name: &str, out: &mut BTreeMap<String, String>) -> bool {
    match pieces.split_first() {
        None => name.is_empty(),
        Some((Piece::Lit(l), rest)) => name.strip_prefix(l.as_str()).is_some_and(|n| match_from(rest, n, out)),
        Some((Piece::Var(v), rest)) => {
            // Shortest first: a placeholder stops at the earliest place the rest matches.
            for end in name
                .char_indices()
                .map(|(i, _)| i)
                .skip(1)
                .chain([name.len()])
                .filter(|&e| e > 0)
            {
                if match_from(rest, &name[end..], out) {
                    out.insert(v.clone(), name[..end].to_string());
                    return true;
                }
            }
            false
        }
    }
}

/// One rename rule.
#[derive(Clone, Debug)]
pub struct Rule {
    pub ours: Pattern,
    pub theirs: Pattern,
    /// The file stores the (2-D) tensor transposed.
    pub transpose: bool,
    /// Where the rule comes from (shown by the README and `inspect`).
    pub source: String,
}

/// The whole table: rules, ignored names and conventions.
#[derive(Clone, Debug)]
pub struct NameTable {
    pub origin: String,
    pub rules: Vec<Rule>,
    pub ignore: Vec<(Pattern, String)>,
    pub conventions: Conventions,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRule {
    ours: String,
    theirs: String,
    #[serde(default)]
    transpose: bool,
    #[serde(default)]
    source: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawIgnore {
    theirs: String,
    #[serde(default)]
    source: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTable {
    conventions: Conventions,
    #[serde(default)]
    rule: Vec<RawRule>,
    #[serde(default)]
    ignore: Vec<RawIgnore>,
}

/// What a name of theirs is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Theirs {
    /// Our tensor of this name (transposed in the file or not).
    Ours { name: String, transpose: bool },
    /// A tensor the network does not use (an `[[ignore]]` pattern matched).
    Ignored,
    /// No rule maps it.
    Unknown,
}

impl NameTable {
    /// The table compiled into the binary.
    pub fn builtin() -> Self {
        // The compiled-in table is tested to parse.
        Self::parse(BUILTIN, "(built in)").unwrap_or_else(|e| panic!("built-in name table: {e}"))
    }

    /// Parses a table (TOML, the layout of `names.toml`); `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, NamesError> {
        let raw: RawTable = toml::from_str(text).map_err(|e| NamesError::Parse {
            origin: origin.to_string(),
            msg: e.to_string(),
        })?;
        if raw.conventions.pad_multiple == 0 {
            return Err(NamesError::Parse {
                origin: origin.into(),
                msg: "conventions.pad_multiple must be positive".into(),
            });
        }
        let mut rules = Vec::with_capacity(raw.rule.len());
        for (index, r) in raw.rule.into_iter().enumerate() {
            let bad = |msg: String| NamesError::BadRule {
                origin: origin.to_string(),
                index,
                ours: r.ours.clone(),
                theirs: r.theirs.clone(),
                msg,
            };
            let ours = Pattern::parse(&r.ours).map_err(bad)?;
            let theirs = Pattern::parse(&r.theirs).map_err(bad)?;
            if ours.vars() != theirs.vars() {
                return Err(bad("both sides must use the same placeholders".into()));
            }
            rules.push(Rule {
                ours,
                theirs,
                transpose: r.transpose,
                source: r.source,
            });
        }
        let ignore = raw
            .ignore
            .into_iter()
            .map(|i| {
                Pattern::parse(&i.theirs)
                    .map(|p| (p, i.source))
                    .map_err(|msg| NamesError::Parse {
                        origin: origin.to_string(),
                        msg,
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            origin: origin.to_string(),
            rules,
            ignore,
            conventions: raw.conventions,
        })
    }

    /// Their name for our tensor `ours`, and whether the file stores it transposed.
    pub fn theirs(&self, ours: &str) -> Option<(String, bool)> {
        self.rules.iter().find_map(|r| {
            r.ours
                .matches(ours)
                .and_then(|v| r.theirs.fill(&v))
                .map(|n| (n, r.transpose))
        })
    }

    /// What a tensor named `theirs` in the file is.
    pub fn ours(&self, theirs: &str) -> Theirs {
        if self.ignore.iter().any(|(p, _)| p.matches(theirs).is_some()) {
            return Theirs::Ignored;
        }
        self.rules
            .iter()
            .find_map(|r| {
                r.theirs
                    .matches(theirs)
                    .and_then(|v| r.ours.fill(&v))
                    .map(|name| Theirs::Ours {
                        name,
                        transpose: r.transpose,
                    })
            })
            .unwrap_or(Theirs::Unknown)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_match_and_fill_both_ways() {
        let p = Pattern::parse("net.pretrained.{rest}").unwrap();
        let v = p.matches("net.pretrained.blocks.3.attn.qkv.weight").unwrap();
        assert_eq!(v["rest"], "blocks.3.attn.qkv.weight");
        assert!(p.matches("net.pretrained.").is_none(), "a placeholder is never empty");
        assert!(p.matches("head.x").is_none());
        let q = Pattern::parse("a.{x}.mid.{y}").unwrap();
        let v = q.matches("a.1.2.mid.3.mid.4").unwrap();
        assert_eq!((v["x"].as_str(), v["y"].as_str()), ("1.2", "3.mid.4"), "shortest first");
        assert_eq!(q.fill(&v).unwrap(), "a.1.2.mid.3.mid.4");
        assert!(Pattern::parse("a.{x}{y}").is_err());
        assert!(Pattern::parse("a.{x").is_err());
        assert!(Pattern::parse("a.{x y}").is_err());
    }

    #[test]
    fn builtin_table_maps_every_tensor_of_ours_and_back() {
        let t = NameTable::builtin();
        let mut cfg = crate::Config::tiny();
        cfg.src_encoder.cls_token = true;
        cfg.src_encoder.layer_scale = true;
        cfg.trunk.layer_scale = true;
        let mut seen = std::collections::BTreeSet::new();
        for name in crate::checkpoint::param_shapes(&cfg).unwrap().keys() {
            let (theirs, transpose) = t.theirs(name).unwrap_or_else(|| panic!("no rule for {name}"));
            assert!(theirs.starts_with("net.") || theirs.starts_with("head."), "{theirs}");
            assert!(seen.insert(theirs.clone()), "two tensors map to {theirs}");
            assert_eq!(
                t.ours(&theirs),
                Theirs::Ours {
                    name: name.clone(),
                    transpose
                },
                "{name} → {theirs} does not map back"
            );
        }
        assert_eq!(
            t.theirs("modulation.conv.bias").unwrap().0,
            "head.scratch.output_conv2.2.bias"
        );
        assert_eq!(t.theirs("trunk.registers").unwrap().0, "net.register_tokens");
        assert_eq!(t.ours("net.pretrained.mask_token"), Theirs::Ignored);
        assert_eq!(t.ours("something.else"), Theirs::Unknown);
        assert_eq!(t.conventions.gain, Gain::Whole);
    }

    #[test]
    fn bad_tables_are_rejected_naming_the_rule() {
        let base = "[conventions]\ngain = \"whole\"\nsource_norm = \"srgb\"\npad_multiple = 16\n";
        let e = NameTable::parse(
            &format!("{base}[[rule]]\nours = \"a.{{x}}\"\ntheirs = \"b.{{y}}\"\n"),
            "t",
        )
        .unwrap_err();
        assert!(e.to_string().contains("same placeholders"), "{e}");
        let e = NameTable::parse(&format!("{base}[[rule]]\nours = \"a\"\n"), "t").unwrap_err();
        assert!(e.to_string().contains("theirs"), "{e}");
        assert!(NameTable::parse(
            "[conventions]\ngain = \"double\"\nsource_norm = \"srgb\"\npad_multiple = 16\n",
            "t"
        )
        .is_err());
    }
}
