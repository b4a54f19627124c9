//! Report files of `pixl eval`, written atomically into the output directory:
//!
//! - `results.md`: a Markdown table in the layout of the paper's Table 1 —
//!   `Method | Lighting cue | PSNR ↑ | SSIM ↑ | LPIPS ↓ | Time (s) ↓` — with the protocol
//!   (dataset, pair count, scale correction, timing device/dtype) stated above it;
//! - `results.json`: the whole [`EvalReport`] (summary rows and per-pair scores);
//! - `per_pair.csv`: `scene,source,target,method,psnr,ssim,lpips`.
//!
//! Conventions: an infinite PSNR (exact prediction) is written `inf` in the table and CSV and as
//! the JSON **string** `"inf"` (JSON has no infinity); a missing LPIPS (no `--lpips` weights) is
//! `—` in the table, an empty CSV field and JSON `null`; a NaN is JSON `null`. Never a made-up
//! number.
use crate::error::{EvalError, Result};
use crate::run::EvalReport;
use std::fmt::Write as _;
use std::path::Path;

/// serde for a score that may be `+∞`: numbers as numbers, `±∞` as the strings `"inf"`/`"-inf"`,
/// NaN as `null` (read back as NaN).
pub mod score {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_nan() {
            s.serialize_none()
        } else if v.is_infinite() {
            s.serialize_str(if *v > 0.0 { "inf" } else { "-inf" })
        } else {
            s.serialize_f64(*v)
        }
    }

    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Repr {
        Num(f64),
        Str(String),
        Null,
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        match Repr::deserialize(d)? {
            Repr::Num(v) => Ok(v),
            Repr::Str(s) if s == "inf" => Ok(f64::INFINITY),
            Repr::Str(s) if s == "-inf" => Ok(f64::NEG_INFINITY),
            Repr::Str(s) => Err(serde::de::Error::custom(format!(
                "expected a number or \"inf\", got {s:?}"
            ))),
            Repr::Null => Ok(f64::NAN),
        }
    }
}

/// A score for a table cell: `inf`, `—` for NaN, else `decimals` digits.
pub fn fmt_score(v: f64, decimals: usize) -> String {
    if v.is_nan() {
        "—".into()
    } else if v.is_infinite() {
        if v > 0.0 { "inf" } else { "-inf" }.into()
    } else {
        format!("{v:.decimals$}")
    }
}

/// The Markdown report (Table 1 layout).
pub fn markdown(report: &EvalReport) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Evaluation\n");
    let _ = writeln!(
        s,
        "- Dataset: `{}`, {} pairs, native target resolution",
        report.dataset, report.pairs
    );
    let _ = writeln!(
        s,
        "- Per-image, per-channel least-squares scale correction: {}",
        if report.scale_correction {
            "on (all methods)"
        } else {
            "off"
        }
    );
    let _ = writeln!(
        s,
        "- LPIPS: {}",
        report
            .lpips_net
            .as_deref()
            .map(|n| format!("v0.1, {n}"))
            .unwrap_or_else(|| "not computed (no --lpips weights)".into())
    );
    if !report.sheet_columns.is_empty() {
        let _ = writeln!(
            s,
            "- Contact sheet{}: the first {} pairs, one row each; columns, left to right: {}",
            report.sheet.as_deref().map(|p| format!(" `{p}`")).unwrap_or_default(),
            report.sheet_pairs,
            report.sheet_columns.join(" | ")
        );
    }
    let _ = writeln!(
        s,
        "- Time: wall-clock of one forward pass on the first pair (intrinsic estimation excluded), mean of the timed runs after the warm-ups\n"
    );
    let _ = writeln!(s, "| Method | Lighting cue | PSNR ↑ | SSIM ↑ | LPIPS ↓ | Time (s) ↓ |");
    let _ = writeln!(s, "|---|---|---:|---:|---:|---:|");
    for m in &report.methods {
        let time = m
            .timing
            .as_ref()
            .map(|t| {
                format!(
                    "{} ({}, {}+{} runs)",
                    fmt_score(t.mean_ms / 1e3, 3),
                    m.device,
                    t.warmups,
                    t.runs_ms.len()
                )
            })
            .unwrap_or_else(|| "—".into());
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} |",
            m.method,
            m.cue,
            fmt_score(m.psnr, 2),
            fmt_score(m.ssim, 3),
            m.lpips.map(|l| fmt_score(l, 3)).unwrap_or_else(|| "—".into()),
            time
        );
    }
    if !report.response.is_empty() {
        let _ = writeln!(
            s,
            "\n## Light response\n\nOver {} lighting pairs (a source relit to its own and to another lighting; renders: {}), per pixel a = the change of log-luminance between the two outputs, b = that between the two renders. Gain = Σab / Σb² (1: all of the light's change shows, 0: none), correlation = Pearson's r (pixl-eval's README).\n",
            report.response[0].pairs,
            report.response_renders.as_deref().unwrap_or("path-traced")
        );
        let _ = writeln!(s, "| Method | Gain ↑ | Correlation ↑ |");
        let _ = writeln!(s, "|---|---:|---:|");
        for r in &report.response {
            let _ = writeln!(
                s,
                "| {} | {} | {} |",
                r.method,
                fmt_score(r.gain, 3),
                fmt_score(r.correlation, 3)
            );
        }
    }
    s
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// `per_pair.csv` contents.
pub fn per_pair_csv(report: &EvalReport) -> String {
    let mut s = String::from("scene,source,target,method,psnr,ssim,lpips\n");
    let num = |v: f64| {
        if v.is_infinite() {
            fmt_score(v, 0)
        } else if v.is_nan() {
            String::new()
        } else {
            format!("{v}")
        }
    };
    for r in &report.per_pair {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{}",
            csv_field(&r.scene),
            csv_field(&r.source),
            csv_field(&r.target),
            csv_field(&r.method),
            num(r.psnr),
            num(r.ssim),
            r.lpips.map(num).unwrap_or_default()
        );
    }
    s
}

/// `results.json` contents (pretty-printed).
pub fn json(report: &EvalReport) -> Result<String> {
    serde_json::to_string_pretty(report).map_err(|e| EvalError::Method {
        method: "report".into(),
        reason: format!("JSON encoding failed: {e}"),
    })
}

/// Writes `results.md`, `results.json` and `per_pair.csv` into `dir` (created if missing).
pub fn write_reports(report: &EvalReport, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|source| EvalError::Io {
        path: dir.to_owned(),
        source,
    })?;
    pixl_core::io::atomic_write_bytes(&dir.join("results.md"), markdown(report).as_bytes())?;
    pixl_core::io::atomic_write_bytes(&dir.join("results.json"), json(report)?.as_bytes())?;
    pixl_core::io::atomic_write_bytes(&dir.join("per_pair.csv"), per_pair_csv(report).as_bytes())?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::{MethodSummary, PairScore};
    use crate::timing::Timing;

    fn report() -> EvalReport {
        EvalReport {
            dataset: "folder:x".into(),
            pairs: 1,
            scale_correction: true,
            lpips_net: None,
            methods: vec![MethodSummary {
                method: "Identity (source)".into(),
                cue: "none".into(),
                pairs: 1,
                psnr: f64::INFINITY,
                ssim: 1.0,
                lpips: None,
                timing: Some(Timing::from_runs(2, vec![1.0, 3.0])),
                device: "cpu f32".into(),
            }],
            per_pair: vec![PairScore {
                scene: "a,b".into(),
                source: "0.png".into(),
                target: "0.png".into(),
                method: "Identity (source)".into(),
                psnr: f64::INFINITY,
                ssim: 1.0,
                lpips: None,
            }],
            response: Vec::new(),
            response_renders: None,
            sheet: None,
            sheet_pairs: 0,
            sheet_columns: Vec::new(),
            sheet_rows: Vec::new(),
        }
    }

    #[test]
    fn json_roundtrips_infinity_as_string() {
        let r = report();
        let text = json(&r).unwrap();
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v["methods"][0]["psnr"], "inf");
        assert!(v["methods"][0]["lpips"].is_null());
        let back: EvalReport = serde_json::from_str(&text).unwrap();
        assert_eq!(back, r);
    }

    #[test]
    fn table_and_csv_layout() {
        let r = report();
        let md = markdown(&r);
        assert!(md.contains("| Method | Lighting cue | PSNR ↑ | SSIM ↑ | LPIPS ↓ | Time (s) ↓ |"));
        assert!(
            md.contains("| Identity (source) | none | inf | 1.000 | — | 0.002 (cpu f32, 2+2 runs) |"),
            "{md}"
        );
        let csv = per_pair_csv(&r);
        assert_eq!(
            csv.lines().nth(1).unwrap(),
            "\"a,b\",0.png,0.png,Identity (source),inf,1,"
        );
    }
}
