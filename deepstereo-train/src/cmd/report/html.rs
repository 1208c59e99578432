//! `report`'s `index.html`: a static page beside report.csv and report.png (relative
//! links only, no scripts, no external resources), so that it opens from the file system.

use deepstereo_core::imageio::RgbImage;
use std::fmt::Write as _;

/// One row of the report's table, as the page shows it.
pub struct PageRow {
    pub method: String,
    pub planes: usize,
    pub views: usize,
    pub scale: u32,
    pub prune: String,
    pub psnr: f64,
    pub ssim: f64,
    pub seconds: f64,
    pub pareto: bool,
}

/// The pictures of one held-out view at the best setting (all at the scene's resolution).
pub struct ViewPictures {
    pub target: usize,
    pub name: String,
    pub truth: RgbImage,
    pub rendered: RgbImage,
    pub plane_sweep: RgbImage,
    pub nearest: RgbImage,
    /// PSNR of the network, the plane sweep and the nearest source against the truth.
    pub psnr: [f64; 3],
}

/// Pictures narrower than this are shown enlarged.
const MIN_SHOWN_WIDTH: u32 = 240;

/// The directory (inside the report's) that holds the best setting's pictures.
pub const BEST_DIR: &str = "best";

/// The file names of view `target`'s pictures, in the order truth, network, plane sweep,
/// nearest source.
pub fn picture_names(target: usize) -> [String; 4] {
    ["truth", "deepstereo", "plane_sweep", "nearest"].map(|k| format!("view_{target:03}_{k}.png"))
}

/// Escapes text for HTML.
pub fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

const STYLE: &str = "body{font-family:sans-serif;margin:2em;max-width:1400px}\
table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:2px 8px;text-align:right}\
td:first-child,th:first-child{text-align:left}tr.pareto{background:#eef6ee}\
figure{display:inline-block;margin:0 8px 8px 0}figcaption{font-size:90%}\
img{image-rendering:pixelated}";

/// The page. `best` is the index into `rows` of the setting the pictures show.
pub fn page(
    heading: &str,
    rows: &[PageRow],
    nearest: Option<(f64, f64)>,
    best: Option<usize>,
    pictures: &[ViewPictures],
) -> String {
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>DeepStereo report</title><style>{STYLE}</style></head><body>\n\
         <h1>Error against run time</h1>\n<p>{}</p>\n\
         <p><img src=\"report.png\" alt=\"PSNR against seconds per image\"></p>\n\
         <p>Data: <a href=\"report.csv\">report.csv</a>, <a href=\"report.md\">report.md</a>.</p>\n",
        escape(heading)
    );
    let header = "<tr><th>method</th><th>planes</th><th>views</th><th>scale</th>\
                  <th>prune</th><th>PSNR (dB)</th><th>SSIM</th><th>s / image</th></tr>\n";
    let row = |h: &mut String, r: &PageRow| {
        let class = if r.pareto { " class=\"pareto\"" } else { "" };
        let _ = writeln!(
            h,
            "<tr{class}><td>{}</td><td>{}</td><td>{}</td><td>1/{}</td><td>{}</td>\
             <td>{:.2}</td><td>{:.3}</td><td>{:.3}</td></tr>",
            escape(&r.method),
            r.planes,
            r.views,
            r.scale,
            escape(&r.prune),
            r.psnr,
            r.ssim,
            r.seconds
        );
    };
    h += "<h2>Pareto front of the network's settings</h2>\n\
          <p>No other setting of the network is both faster and better (PSNR).</p>\n<table>\n";
    h += header;
    rows.iter()
        .filter(|r| r.pareto)
        .for_each(|r| row(&mut h, r));
    h += "</table>\n<h2>Every setting</h2>\n<p>Rows on the Pareto front are shaded.</p>\n<table>\n";
    h += header;
    rows.iter().for_each(|r| row(&mut h, r));
    if let Some((p, s)) = nearest {
        let _ = writeln!(
            h,
            "<tr><td>nearest source</td><td>-</td><td>1</td><td>-</td><td>-</td>\
             <td>{p:.2}</td><td>{s:.3}</td><td>-</td></tr>"
        );
    }
    h += "</table>\n";
    if let Some(b) = best.and_then(|b| rows.get(b)) {
        best_section(&mut h, b, pictures);
    }
    h += "</body></html>\n";
    h
}

/// The best setting's section: its heading and each held-out view's photograph beside
/// its renders (the pictures in [`BEST_DIR`]).
fn best_section(h: &mut String, b: &PageRow, pictures: &[ViewPictures]) {
    let _ = writeln!(
        h,
        "<h2>The best setting: {} at {} planes, {} views, scale 1/{}, prune {}</h2>\n\
         <p>Each held-out view: the photograph, the network's render, the classical plane \
         sweep on the same sources and planes, and the nearest source view.</p>",
        escape(&b.method),
        b.planes,
        b.views,
        b.scale,
        escape(&b.prune)
    );
    for v in pictures {
        let names = picture_names(v.target);
        let captions = [
            "photograph (held out)".to_string(),
            format!("DeepStereo, {:.2} dB", v.psnr[0]),
            format!("plane sweep, {:.2} dB", v.psnr[1]),
            format!("nearest source, {:.2} dB", v.psnr[2]),
        ];
        let _ = writeln!(h, "<h3>View {} ({})</h3>\n<div>", v.target, escape(&v.name));
        // Small renders are shown enlarged by a whole factor (pixelated, not blurred).
        let zoom = MIN_SHOWN_WIDTH.div_ceil(v.truth.width.max(1)).max(1);
        for (n, c) in names.iter().zip(&captions) {
            let _ = writeln!(
                h,
                "<figure><img src=\"{BEST_DIR}/{n}\" width=\"{}\" height=\"{}\" alt=\"{}\">\
                 <figcaption>{}</figcaption></figure>",
                v.truth.width * zoom,
                v.truth.height * zoom,
                escape(c),
                escape(c)
            );
        }
        *h += "</div>\n";
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn page_links_only_relative_files_and_escapes_text() {
        let rows = [PageRow {
            method: "deepstereo-<candle>".into(),
            planes: 8,
            views: 4,
            scale: 1,
            prune: "off".into(),
            psnr: 20.0,
            ssim: 0.5,
            seconds: 1.0,
            pareto: true,
        }];
        let img = RgbImage::new(2, 2);
        let pics = [ViewPictures {
            target: 3,
            name: "a&b".into(),
            truth: img.clone(),
            rendered: img.clone(),
            plane_sweep: img.clone(),
            nearest: img,
            psnr: [1.0, 2.0, 3.0],
        }];
        let h = page("scene", &rows, Some((1.0, 0.1)), Some(0), &pics);
        assert!(h.contains("deepstereo-&lt;candle&gt;") && h.contains("a&amp;b"));
        assert!(h.contains("best/view_003_truth.png") && !h.contains("http"));
        assert!(!h.contains("<script"));
    }
}
