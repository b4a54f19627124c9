//! A self-contained HTML report: rows of captioned image panels, images inlined as base64 PNG.
use anyhow::Result;
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

pub struct Report {
    pub title: String,
    pub notes: Vec<String>,
    pub rows: Vec<Row>,
}

fn png_bytes(img: &Image) -> Vec<u8> {
    use image::ImageEncoder;
    let bytes: Vec<u8> = img
        .data
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let color = match img.channels {
        1 => image::ExtendedColorType::L8,
        4 => image::ExtendedColorType::Rgba8,
        _ => image::ExtendedColorType::Rgb8,
    };
    let mut out = Vec::new();
    // Encoding an in-memory buffer of the right size cannot fail; an empty image yields no bytes.
    let _ =
        image::codecs::png::PngEncoder::new(&mut out).write_image(&bytes, img.width as u32, img.height as u32, color);
    out
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

impl Report {
    pub fn to_html(&self) -> Result<String> {
        let mut h = String::new();
        h.push_str("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\">");
        h.push_str(&format!("<title>{}</title>", escape(&self.title)));
        h.push_str(
            "<style>body{font-family:sans-serif;margin:1.5em;background:#fafafa}figure{display:inline-block;\
             margin:4px;text-align:center;vertical-align:top}img{image-rendering:pixelated;width:200px;border:1px solid #ccc}\
             figcaption{font-size:12px}.m{color:#333;font-weight:bold}h2{margin-bottom:4px}</style></head><body>\n",
        );
        h.push_str(&format!("<h1>{}</h1>\n", escape(&self.title)));
        for n in &self.notes {
            h.push_str(&format!("<p>{}</p>\n", escape(n)));
        }
        for row in &self.rows {
            h.push_str(&format!("<section class=\"row\"><h2>{}</h2>\n", escape(&row.title)));
            for p in &row.panels {
                h.push_str(&format!(
                    "<figure class=\"panel\"><img alt=\"{}\" src=\"data:image/png;base64,{}\"><figcaption>{}",
                    escape(&p.label),
                    base64(&p.png),
                    escape(&p.label)
                ));
                if let Some(c) = &p.caption {
                    h.push_str(&format!("<br><span class=\"m\">{}</span>", escape(c)));
                }
                h.push_str("</figcaption></figure>\n");
            }
            h.push_str("</section>\n");
        }
        h.push_str("</body></html>\n");
        Ok(h)
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
}
