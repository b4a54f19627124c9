//! A self-contained HTML report (`pixl demo`'s): a plain-language introduction, summary tables, then one row of
//! captioned image panels per case. Images are inlined as base64 PNG; a click on one opens it at
//! full size in an overlay (inline CSS/JS, nothing fetched). Each row is a grid that keeps its
//! panels on one line and scrolls sideways on narrow screens instead of wrapping.
use pixl_core::Image;

pub struct Panel {
    pub label: String,
    pub png: Vec<u8>,
    pub caption: Option<String>,
}

impl Panel {
    /// Encodes `img` (values in [0, 1], clamped) as an 8-bit PNG.
    pub fn new(label: &str, img: &Image, caption: Option<String>) -> Self {
        Panel {
            label: label.into(),
            png: png_bytes(img),
            caption,
        }
    }
}

pub struct Row {
    pub title: String,
    pub panels: Vec<Panel>,
}

/// A table of numbers: one row per case, one column per method; the best value of each row
/// (highest, or lowest where `lower_is_better`) is set in bold.
pub struct Table {
    pub caption: String,
    pub row_header: String,
    pub columns: Vec<String>,
    /// `(row label, one value per column)`; `None` where a method has no value.
    pub rows: Vec<(String, Vec<Option<f64>>)>,
    pub decimals: usize,
    pub lower_is_better: bool,
}

pub struct Report {
    pub title: String,
    /// The first paragraph: what the reader is looking at, in plain words.
    pub intro: String,
    pub tables: Vec<Table>,
    pub notes: Vec<String>,
    pub rows: Vec<Row>,
}

/// 8-bit PNG bytes of `img` (the report's panels; an image that cannot be encoded shows empty).
fn png_bytes(img: &Image) -> Vec<u8> {
    pixl_core::io::encode_png(
        img,
        pixl_core::io::PngDepth::Eight,
        pixl_core::io::PngCompression::Default,
    )
    .unwrap_or_default()
}

/// Standard base64 (RFC 4648) with padding.
pub fn base64(bytes: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [chunk[0], *chunk.get(1).unwrap_or(&0), *chunk.get(2).unwrap_or(&0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= chunk.len() {
                s.push(T[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

const STYLE: &str = "body{font-family:sans-serif;margin:1.5em;background:#fafafa;color:#222;max-width:1800px}\
p.intro{font-size:1.05em;max-width:60em;line-height:1.45}p.note{font-size:.9em;color:#444;max-width:70em}\
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:3px 9px;text-align:right}\
th:first-child,td:first-child{text-align:left}caption{text-align:left;font-weight:bold;padding:4px 0}\
section.row{margin-bottom:1.2em}section.row h2{margin:0 0 4px;font-size:1.1em}\
div.grid{display:grid;grid-auto-flow:column;grid-auto-columns:minmax(110px,1fr);gap:6px;overflow-x:auto}\
figure{margin:0;text-align:center}figure img{width:100%;image-rendering:pixelated;border:1px solid #ccc;cursor:zoom-in}\
figcaption{font-size:12px}.m{color:#333;font-weight:bold}\
#zoom{display:none;position:fixed;inset:0;background:rgba(0,0,0,.85);align-items:center;justify-content:center;cursor:zoom-out}\
#zoom.on{display:flex}#zoom img{max-width:96vw;max-height:90vh;min-width:min(60vw,60vh);image-rendering:pixelated}\
#zoom p{position:fixed;bottom:8px;color:#eee;width:100%;text-align:center;margin:0}";

/// Opens a clicked panel's image in the overlay at full size; Escape or a click closes it.
const SCRIPT: &str = "const z=document.getElementById('zoom'),zi=z.querySelector('img'),zp=z.querySelector('p');\
document.querySelectorAll('figure img').forEach(i=>i.addEventListener('click',()=>{zi.src=i.src;\
zp.textContent=i.dataset.title+' \u{2014} '+i.naturalWidth+'\u{d7}'+i.naturalHeight+' px';z.classList.add('on')}));\
z.addEventListener('click',()=>z.classList.remove('on'));\
document.addEventListener('keydown',e=>{if(e.key==='Escape')z.classList.remove('on')});";

impl Table {
    fn best(&self, values: &[Option<f64>]) -> Option<f64> {
        let better = |a: f64, b: f64| if self.lower_is_better { a < b } else { a > b };
        values.iter().flatten().copied().fold(None, |best, v| match best {
            Some(b) if !better(v, b) => Some(b),
            _ => Some(v),
        })
    }

    fn to_html(&self) -> String {
        let mut h = format!(
            "<table class=\"summary\"><caption>{}</caption><tr><th>{}</th>",
            escape(&self.caption),
            escape(&self.row_header)
        );
        for c in &self.columns {
            h.push_str(&format!("<th>{}</th>", escape(c)));
        }
        h.push_str("</tr>\n");
        for (label, values) in &self.rows {
            let best = self.best(values);
            h.push_str(&format!("<tr><td>{}</td>", escape(label)));
            for v in values {
                let cell = match v {
                    None => "\u{2013}".to_string(),
                    Some(x) if x.is_infinite() => "\u{221e}".to_string(),
                    Some(x) => format!("{x:.*}", self.decimals),
                };
                if v.is_some() && *v == best {
                    h.push_str(&format!("<td><b>{cell}</b></td>"));
                } else {
                    h.push_str(&format!("<td>{cell}</td>"));
                }
            }
            h.push_str("</tr>\n");
        }
        h.push_str("</table>\n");
        h
    }
}

impl Report {
    pub fn to_html(&self) -> String {
        let mut h = String::new();
        h.push_str("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\">");
        h.push_str("<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">");
        h.push_str(&format!(
            "<title>{}</title><style>{STYLE}</style></head><body>\n",
            escape(&self.title)
        ));
        h.push_str(&format!(
            "<h1>{}</h1>\n<p class=\"intro\">{}</p>\n",
            escape(&self.title),
            escape(&self.intro)
        ));
        for t in &self.tables {
            h.push_str(&t.to_html());
        }
        for n in &self.notes {
            h.push_str(&format!("<p class=\"note\">{}</p>\n", escape(n)));
        }
        for row in &self.rows {
            h.push_str(&format!(
                "<section class=\"row\"><h2>{}</h2><div class=\"grid\">\n",
                escape(&row.title)
            ));
            for p in &row.panels {
                h.push_str(&format!(
                    "<figure class=\"panel\"><img alt=\"{}\" src=\"data:image/png;base64,{}\" data-title=\"{}\"><figcaption>{}",
                    escape(&p.label),
                    base64(&p.png),
                    escape(&format!("{}: {}", row.title, p.label)),
                    escape(&p.label)
                ));
                if let Some(c) = &p.caption {
                    h.push_str(&format!("<br><span class=\"m\">{}</span>", escape(c)));
                }
                h.push_str("</figcaption></figure>\n");
            }
            h.push_str("</div></section>\n");
        }
        h.push_str("<div id=\"zoom\"><img alt=\"full size\"><p></p></div>\n");
        h.push_str(&format!("<script>{SCRIPT}</script>\n</body></html>\n"));
        h
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_known_vectors() {
        // RFC 4648 §10 test vectors.
        for (i, o) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(i.as_bytes()), o);
        }
    }

    #[test]
    fn summary_table_bolds_the_best_of_each_row() {
        let t = Table {
            caption: "PSNR".into(),
            row_header: "preset".into(),
            columns: vec!["a".into(), "b".into(), "c".into()],
            rows: vec![
                ("p1".into(), vec![Some(10.0), Some(12.5), None]),
                ("p2".into(), vec![Some(f64::INFINITY), Some(3.0), Some(4.0)]),
            ],
            decimals: 2,
            lower_is_better: false,
        };
        let h = t.to_html();
        assert!(
            h.contains("<tr><td>p1</td><td>10.00</td><td><b>12.50</b></td><td>\u{2013}</td></tr>"),
            "{h}"
        );
        assert!(
            h.contains("<tr><td>p2</td><td><b>\u{221e}</b></td><td>3.00</td><td>4.00</td></tr>"),
            "{h}"
        );
        let lower = Table {
            lower_is_better: true,
            ..t
        };
        let h = lower.to_html();
        assert!(h.contains("<td>p1</td><td><b>10.00</b></td><td>12.50</td>"), "{h}");
        assert!(h.contains("<td>p2</td><td>\u{221e}</td><td><b>3.00</b></td>"), "{h}");
    }
}
