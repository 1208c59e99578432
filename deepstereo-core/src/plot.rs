//! Minimal raster line and scatter plots as PNG-ready images (no font or plotting
//! dependency): axes with tick labels in a built-in 5x7 bitmap font, series as lines or
//! markers, a legend.

use crate::imageio::RgbImage;

/// 5x7 glyphs, one byte per row (low 5 bits, MSB = leftmost column).
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        '0' => [14, 17, 19, 21, 25, 17, 14],
        '1' => [4, 12, 4, 4, 4, 4, 14],
        '2' => [14, 17, 1, 2, 4, 8, 31],
        '3' => [31, 2, 4, 2, 1, 17, 14],
        '4' => [2, 6, 10, 18, 31, 2, 2],
        '5' => [31, 16, 30, 1, 1, 17, 14],
        '6' => [6, 8, 16, 30, 17, 17, 14],
        '7' => [31, 1, 2, 4, 8, 8, 8],
        '8' => [14, 17, 17, 14, 17, 17, 14],
        '9' => [14, 17, 17, 15, 1, 2, 12],
        '.' => [0, 0, 0, 0, 0, 12, 12],
        '-' => [0, 0, 0, 31, 0, 0, 0],
        '+' => [0, 4, 4, 31, 4, 4, 0],
        '/' => [1, 1, 2, 4, 8, 16, 16],
        '(' => [2, 4, 8, 8, 8, 4, 2],
        ')' => [8, 4, 2, 2, 2, 4, 8],
        ':' => [0, 12, 12, 0, 12, 12, 0],
        '=' => [0, 0, 31, 0, 31, 0, 0],
        '_' => [0, 0, 0, 0, 0, 0, 31],
        'A' => [14, 17, 17, 31, 17, 17, 17],
        'B' => [30, 17, 17, 30, 17, 17, 30],
        'C' => [14, 17, 16, 16, 16, 17, 14],
        'D' => [28, 18, 17, 17, 17, 18, 28],
        'E' => [31, 16, 16, 30, 16, 16, 31],
        'F' => [31, 16, 16, 30, 16, 16, 16],
        'G' => [14, 17, 16, 23, 17, 17, 15],
        'H' => [17, 17, 17, 31, 17, 17, 17],
        'I' => [14, 4, 4, 4, 4, 4, 14],
        'J' => [7, 2, 2, 2, 2, 18, 12],
        'K' => [17, 18, 20, 24, 20, 18, 17],
        'L' => [16, 16, 16, 16, 16, 16, 31],
        'M' => [17, 27, 21, 21, 17, 17, 17],
        'N' => [17, 17, 25, 21, 19, 17, 17],
        'O' => [14, 17, 17, 17, 17, 17, 14],
        'P' => [30, 17, 17, 30, 16, 16, 16],
        'Q' => [14, 17, 17, 17, 21, 18, 13],
        'R' => [30, 17, 17, 30, 20, 18, 17],
        'S' => [15, 16, 16, 14, 1, 1, 30],
        'T' => [31, 4, 4, 4, 4, 4, 4],
        'U' => [17, 17, 17, 17, 17, 17, 14],
        'V' => [17, 17, 17, 17, 17, 10, 4],
        'W' => [17, 17, 17, 21, 21, 21, 10],
        'X' => [17, 17, 10, 4, 10, 17, 17],
        'Y' => [17, 17, 10, 4, 4, 4, 4],
        'Z' => [31, 1, 2, 4, 8, 16, 31],
        _ => [0; 7],
    }
}

/// A series to draw.
pub struct Series {
    pub label: String,
    pub colour: [f32; 3],
    pub points: Vec<(f64, f64)>,
    /// Join points with lines (else markers only).
    pub line: bool,
    /// Marker half-size in pixels (0: none).
    pub marker: i32,
    /// A short text drawn next to each point (empty: none; else one per point).
    pub labels: Vec<String>,
}

const W: i32 = 900;
const H: i32 = 480;
const LEFT: i32 = 70;
/// The legend sits right of the plot area, so that it never hides a point (at least this
/// wide; wider for long labels).
const RIGHT: i32 = 220;
/// Offset of the legend's text from the plot area's right edge.
const LEGEND_TEXT: i32 = 32;
const TOP: i32 = 30;
const BOTTOM: i32 = 50;

fn put(img: &mut RgbImage, x: i32, y: i32, c: [f32; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width && (y as u32) < img.height {
        let i = ((y as u32 * img.width + x as u32) * 3) as usize;
        img.data[i..i + 3].copy_from_slice(&c);
    }
}

/// Draws `text` with its top-left corner at `(x, y)`.
pub fn text(img: &mut RgbImage, x: i32, y: i32, s: &str, c: [f32; 3]) {
    for (k, ch) in s.chars().enumerate() {
        for (r, row) in glyph(ch).iter().enumerate() {
            for col in 0..5 {
                if row & (16 >> col) != 0 {
                    put(img, x + k as i32 * 6 + col, y + r as i32, c);
                }
            }
        }
    }
}

fn line(img: &mut RgbImage, (x0, y0): (i32, i32), (x1, y1): (i32, i32), c: [f32; 3]) {
    let n = (x1 - x0).abs().max((y1 - y0).abs()).max(1);
    for i in 0..=n {
        let t = i as f64 / n as f64;
        put(
            img,
            x0 + ((x1 - x0) as f64 * t).round() as i32,
            y0 + ((y1 - y0) as f64 * t).round() as i32,
            c,
        );
    }
}

/// Distinct colours (Okabe-Ito, then Tableau), for series that do not pick their own, and
/// for a series whose colour an earlier series already took.
pub const PALETTE: [[f32; 3]; 10] = [
    [0.84, 0.37, 0.0],
    [0.0, 0.45, 0.70],
    [0.0, 0.62, 0.45],
    [0.80, 0.47, 0.65],
    [0.90, 0.62, 0.0],
    [0.34, 0.71, 0.91],
    [0.55, 0.34, 0.29],
    [0.58, 0.40, 0.74],
    [0.74, 0.74, 0.13],
    [0.84, 0.15, 0.16],
];

/// Colour number `k` beyond the palette: hues a golden angle apart, so none repeats.
fn extra_colour(k: usize) -> [f32; 3] {
    let h = (k as f32 * 0.618_034).fract() * 6.0;
    let (v, s) = (0.75f32, 0.8f32);
    let f = h - h.floor();
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    match h as u32 {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

/// Marker shapes, one per series in turn (a series' shape is its index modulo these).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shape {
    Square,
    Circle,
    Triangle,
    Diamond,
    Cross,
    Plus,
    HollowSquare,
}

const SHAPES: [Shape; 7] = [
    Shape::Square,
    Shape::Circle,
    Shape::Triangle,
    Shape::Diamond,
    Shape::Cross,
    Shape::Plus,
    Shape::HollowSquare,
];

/// The marker shape of series `k`.
pub fn shape_of(k: usize) -> Shape {
    SHAPES[k % SHAPES.len()]
}

/// Ticks aimed for on an axis.
const TICKS: f64 = 6.0;
/// Glyph advance and height of the bitmap font, in pixels.
const GLYPH_W: i32 = 6;
const GLYPH_H: i32 = 7;

/// Whether pixel `(dx, dy)` from a marker's centre belongs to a marker of half-size `r`.
fn in_marker(shape: Shape, dx: i32, dy: i32, r: i32) -> bool {
    let (ax, ay) = (dx.abs(), dy.abs());
    match shape {
        Shape::Square => ax <= r && ay <= r,
        Shape::Circle => dx * dx + dy * dy <= r * r + r,
        // Apex up, base at dy = r.
        Shape::Triangle => dy <= r && 2 * ax <= dy + r,
        Shape::Diamond => ax + ay <= r + 1,
        Shape::Cross => (ax == ay || (ax - ay).abs() == 1) && ax <= r + 1,
        Shape::Plus => (ax <= 1 && ay <= r + 1) || (ay <= 1 && ax <= r + 1),
        Shape::HollowSquare => ax <= r && ay <= r && (ax >= r - 1 || ay >= r - 1),
    }
}

fn marker(img: &mut RgbImage, (x, y): (i32, i32), shape: Shape, r: i32, c: [f32; 3]) {
    for dy in -r - 1..=r + 1 {
        for dx in -r - 1..=r + 1 {
            if in_marker(shape, dx, dy, r) {
                put(img, x + dx, y + dy, c);
            }
        }
    }
}

/// Room around the data range `[lo, hi]` of an axis: `share` of its span, or, when the
/// span is nil next to the values (one point, or all equal), 5% of their magnitude (at
/// least 0.05), so that the axis still shows distinct round ticks.
fn pad(lo: f64, hi: f64, share: f64) -> f64 {
    let size = lo.abs().max(hi.abs()).max(1.0);
    match hi - lo > 1e-9 * size {
        true => (hi - lo) * share,
        false => 0.05 * size,
    }
}

/// Round tick values (1, 2 or 5 times a power of ten apart) inside `[lo, hi]`, at least
/// 1 apart when `integer`.
pub fn nice_ticks(lo: f64, hi: f64, integer: bool) -> (Vec<f64>, f64) {
    let span = (hi - lo).max(1e-12);
    let raw = span / TICKS;
    let mag = 10f64.powf(raw.log10().floor());
    let mut step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    if integer {
        step = step.max(1.0).round();
    }
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    let ticks = (first..=last).map(|i| i as f64 * step).collect();
    (ticks, step)
}

/// Ticks of a log10 axis spanning `[lo, hi]` (in log10 units): 1, 2 and 5 times each
/// power of ten, or only the powers when those are too many; linear round ticks of the
/// values when the span is under one of them.
fn log_ticks(lo: f64, hi: f64) -> Vec<f64> {
    let (a, b) = (lo.floor() as i32, hi.ceil() as i32);
    let within = |v: &f64| (lo..=hi).contains(&v.log10());
    for mults in [&[1.0, 2.0, 5.0][..], &[1.0][..]] {
        let t: Vec<f64> = (a..=b)
            .flat_map(|e| mults.iter().map(move |m| m * 10f64.powi(e)))
            .filter(within)
            .collect();
        if t.len() >= 2 && t.len() as f64 <= TICKS + 2.0 {
            return t;
        }
        if t.len() > TICKS as usize + 2 {
            continue;
        }
        break;
    }
    let (t, _) = nice_ticks(10f64.powf(lo), 10f64.powf(hi), false);
    t.into_iter().filter(|v| *v > 0.0).collect()
}

/// Tick labels with as many decimals as the closest two ticks need to differ.
fn tick_labels(ticks: &[f64]) -> Vec<String> {
    let gap = ticks
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .fold(f64::MAX, f64::min);
    let min_abs = ticks
        .iter()
        .map(|t| t.abs())
        .filter(|t| *t > 0.0)
        .fold(f64::MAX, f64::min);
    let need = gap.min(min_abs);
    // The tolerance keeps a gap of 0.0999999 (0.1 in floating point) at one decimal.
    let decimals = if need.is_finite() && need < 1.0 && need > 0.0 {
        (-need.log10() - 1e-6).ceil() as usize
    } else {
        0
    };
    ticks
        .iter()
        .map(|t| format!("{:.*}", decimals.min(6), t))
        .collect()
}

/// Log-axis tick labels: each value with the decimals it needs (0.002, 0.01, 0.5, 2, 10).
fn log_tick_labels(ticks: &[f64]) -> Vec<String> {
    ticks
        .iter()
        .map(|&t| {
            let decimals = if t > 0.0 && t < 1.0 {
                ((-t.log10()).ceil() as usize).min(6)
            } else {
                0
            };
            format!("{t:.decimals$}")
        })
        .collect()
}

/// A pixel rectangle `(x0, y0, x1, y1)`, inclusive.
type Rect = (i32, i32, i32, i32);

fn overlaps(a: Rect, b: Rect) -> bool {
    a.0 <= b.2 && b.0 <= a.2 && a.1 <= b.3 && b.1 <= a.3
}

/// Whether a point has both coordinates finite (others are not drawn).
fn finite(p: &(f64, f64)) -> bool {
    p.0.is_finite() && p.1.is_finite()
}

/// The data-to-pixel mapping of the plot area: x (log10 when `log_x`) in `x0..x1` to
/// `LEFT..plot_r`, y in `y0..y1` to `H - BOTTOM..TOP`.
struct Frame {
    log_x: bool,
    /// Every finite x is an integer (step counts): ticks at integers.
    integer_x: bool,
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
    plot_r: i32,
}

impl Frame {
    /// The finite points' range with margins of 5% (x) and 8% (y); `0..1` when there are
    /// none.
    fn fit(series: &[Series], log_x: bool, plot_r: i32) -> Self {
        let tx = |x: f64| if log_x { x.max(1e-12).log10() } else { x };
        let pts: Vec<(f64, f64)> = series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|p| finite(p))
            .cloned()
            .collect();
        let integer_x = !log_x && !pts.is_empty() && pts.iter().all(|p| p.0.fract() == 0.0);
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in &pts {
            (x0, x1, y0, y1) = (x0.min(tx(x)), x1.max(tx(x)), y0.min(y), y1.max(y));
        }
        if x0 > x1 {
            (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
        }
        let (px, py) = (pad(x0, x1, 0.05), pad(y0, y1, 0.08));
        Self {
            log_x,
            integer_x,
            x0: x0 - px,
            x1: x1 + px,
            y0: y0 - py,
            y1: y1 + py,
            plot_r,
        }
    }

    /// The pixel column of an axis value (log10 of x on a log axis).
    fn sxt(&self, t: f64) -> i32 {
        LEFT + ((t - self.x0) / (self.x1 - self.x0) * (self.plot_r - LEFT) as f64) as i32
    }

    /// The pixel column of x.
    fn sx(&self, x: f64) -> i32 {
        self.sxt(if self.log_x { x.max(1e-12).log10() } else { x })
    }

    /// The pixel row of y.
    fn sy(&self, y: f64) -> i32 {
        H - BOTTOM - ((y - self.y0) / (self.y1 - self.y0) * (H - TOP - BOTTOM) as f64) as i32
    }
}

/// A plot of `series` with axis titles; `log_x` plots x on a log10 scale. Each series gets
/// its own marker shape (by index) and colour (an already used colour is replaced from
/// [`PALETTE`]); point labels are placed where they overlap no other label, or left out;
/// ticks sit at round values, at integers when every x is an integer (step counts).
pub fn plot(title: &str, x_title: &str, y_title: &str, series: &[Series], log_x: bool) -> RgbImage {
    // The plot area keeps its width; the legend's column grows to fit its longest label.
    let plot_r = W - RIGHT;
    let longest = series.iter().map(|s| s.label.len()).max().unwrap_or(0) as i32;
    let width = W.max(plot_r + LEGEND_TEXT + GLYPH_W * longest + GLYPH_W);
    let mut img = RgbImage::new(width as u32, H as u32);
    img.data.iter_mut().for_each(|v| *v = 1.0);
    let frame = Frame::fit(series, log_x, plot_r);
    draw_axes(&mut img, &frame, (title, x_title, y_title));
    let colours = series_colours(series);
    let taken = draw_series(&mut img, &frame, series, &colours);
    draw_point_labels(&mut img, &frame, series, &colours, taken);
    draw_legend(&mut img, series, &colours, plot_r);
    img
}

const GREY: [f32; 3] = [0.85, 0.85, 0.85];
const BLACK: [f32; 3] = [0.0, 0.0, 0.0];

/// Grid lines and tick labels, the axes, and the titles `(plot, x axis, y axis)`.
fn draw_axes(img: &mut RgbImage, f: &Frame, (title, x_title, y_title): (&str, &str, &str)) {
    let plot_r = f.plot_r;
    let xticks = if f.log_x {
        log_ticks(f.x0, f.x1)
    } else {
        nice_ticks(f.x0, f.x1, f.integer_x).0
    };
    let xlabels = if f.log_x {
        log_tick_labels(&xticks)
    } else {
        tick_labels(&xticks)
    };
    for (v, l) in xticks.iter().zip(xlabels) {
        let gx = f.sx(*v);
        line(img, (gx, TOP), (gx, H - BOTTOM), GREY);
        text(
            img,
            gx - GLYPH_W / 2 * l.len() as i32,
            H - BOTTOM + 6,
            &l,
            BLACK,
        );
    }
    let yticks = nice_ticks(f.y0, f.y1, false).0;
    for (v, l) in yticks.iter().zip(tick_labels(&yticks)) {
        let gy = f.sy(*v);
        line(img, (LEFT, gy), (plot_r, gy), GREY);
        text(img, LEFT - 6 - GLYPH_W * l.len() as i32, gy - 3, &l, BLACK);
    }
    line(img, (LEFT, H - BOTTOM), (plot_r, H - BOTTOM), BLACK);
    line(img, (LEFT, TOP), (LEFT, H - BOTTOM), BLACK);
    // The title above the y axis title (rows 3-9 against 16-22), which runs past `LEFT`.
    text(img, LEFT, 3, title, BLACK);
    text(
        img,
        (LEFT + plot_r - GLYPH_W * x_title.len() as i32) / 2,
        H - 18,
        x_title,
        BLACK,
    );
    text(img, 4, TOP - 14, y_title, BLACK);
}

/// Each series' colour: its own, or when an earlier series already has it the first
/// unused colour of [`PALETTE`] (then generated ones).
fn series_colours(series: &[Series]) -> Vec<[f32; 3]> {
    let mut used: Vec<[f32; 3]> = Vec::new();
    series
        .iter()
        .map(|s| {
            let c = if used.contains(&s.colour) {
                let spare = PALETTE.iter().find(|p| !used.contains(p)).copied();
                spare.unwrap_or_else(|| extra_colour(used.len()))
            } else {
                s.colour
            };
            used.push(c);
            c
        })
        .collect()
}

/// The series' lines and markers; returns every marker's box, so that labels avoid
/// markers too.
fn draw_series(
    img: &mut RgbImage,
    f: &Frame,
    series: &[Series],
    colours: &[[f32; 3]],
) -> Vec<Rect> {
    let mut taken: Vec<Rect> = Vec::new();
    for (k, s) in series.iter().enumerate() {
        let screen: Vec<(i32, i32)> = s
            .points
            .iter()
            .filter(|p| finite(p))
            .map(|&(x, y)| (f.sx(x), f.sy(y)))
            .collect();
        let c = colours[k];
        if s.line {
            for w in screen.windows(2) {
                line(img, w[0], w[1], c);
            }
        }
        if s.marker > 0 {
            let r = s.marker;
            for &p in &screen {
                marker(img, p, shape_of(k), r, c);
                taken.push((p.0 - r - 1, p.1 - r - 1, p.0 + r + 1, p.1 + r + 1));
            }
        }
    }
    taken
}

/// Point labels, each at the first of six places around its point that stays inside the
/// plot area and overlaps no marker and no earlier label (else left out).
fn draw_point_labels(
    img: &mut RgbImage,
    f: &Frame,
    series: &[Series],
    colours: &[[f32; 3]],
    mut taken: Vec<Rect>,
) {
    let plot_r = f.plot_r;
    for (k, s) in series.iter().enumerate() {
        let labelled = s.points.iter().zip(&s.labels).filter(|(p, _)| finite(p));
        for ((x, y), l) in labelled {
            let (px, py, r) = (f.sx(*x), f.sy(*y), s.marker.max(1) + 2);
            let (w, h) = (GLYPH_W * l.len() as i32, GLYPH_H);
            let candidates = [
                (px + r, py - h - 1),
                (px + r, py + 2),
                (px - r - w, py - h - 1),
                (px - r - w, py + 2),
                (px - w / 2, py - r - h),
                (px - w / 2, py + r + 1),
            ];
            let free = candidates.iter().copied().find(|&(lx, ly)| {
                let rect = (lx - 1, ly - 1, lx + w, ly + h);
                let inside = lx > LEFT && lx + w < plot_r && ly > TOP && ly + h < H - BOTTOM;
                inside && !taken.iter().any(|t| overlaps(*t, rect))
            });
            if let Some((lx, ly)) = free {
                taken.push((lx - 1, ly - 1, lx + w, ly + h));
                text(img, lx, ly, l, colours[k]);
            }
        }
    }
}

/// The legend right of the plot area: each series' line and marker, and its label.
fn draw_legend(img: &mut RgbImage, series: &[Series], colours: &[[f32; 3]], plot_r: i32) {
    for (k, s) in series.iter().enumerate() {
        let c = colours[k];
        let ly = TOP + 6 + 14 * k as i32;
        let (lx, mid) = (plot_r + 10, ly + 3);
        if s.line {
            line(img, (lx, mid), (lx + 16, mid), c);
            line(img, (lx, mid + 1), (lx + 16, mid + 1), c);
        }
        if s.marker > 0 {
            marker(img, (lx + 8, mid), shape_of(k), s.marker.min(3), c);
        }
        text(img, plot_r + LEGEND_TEXT, ly, &s.label, BLACK);
    }
}

/// Indices of the points on the Pareto front (lower x and higher y are better).
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].0.is_finite() && points[i].1.is_finite())
        .collect();
    idx.sort_by(|&a, &b| {
        points[a]
            .0
            .total_cmp(&points[b].0)
            .then(points[b].1.total_cmp(&points[a].1))
    });
    let mut front = Vec::new();
    let mut best = f64::MIN;
    for i in idx {
        if points[i].1 > best {
            best = points[i].1;
            front.push(i);
        }
    }
    front
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_keeps_only_undominated_points() {
        let p = [
            (1.0, 20.0),
            (2.0, 25.0),
            (3.0, 24.0),
            (4.0, 30.0),
            (0.5, 10.0),
        ];
        assert_eq!(pareto_front(&p), vec![4, 0, 1, 3]);
    }

    #[test]
    fn ticks_are_round_unique_and_integer_for_steps() {
        let (t, step) = nice_ticks(-3.2, 4103.0, true);
        assert_eq!(step, 1000.0);
        assert_eq!(t, vec![0.0, 1000.0, 2000.0, 3000.0, 4000.0]);
        let (t, _) = nice_ticks(0.0, 5.4, true);
        assert!(t.iter().all(|v| v.fract() == 0.0), "{t:?}");
        let (t, _) = nice_ticks(27.1, 28.3, false);
        let l = tick_labels(&t);
        assert_eq!(l, vec!["27.2", "27.4", "27.6", "27.8", "28.0", "28.2"]);
        let lt = log_tick_labels(&log_ticks(0.3f64.log10(), 5.0f64.log10()));
        assert_eq!(lt, vec!["0.5", "1", "2", "5"]);
        let lt = log_tick_labels(&log_ticks(0.0015f64.log10(), 0.25f64.log10()));
        assert_eq!(
            lt,
            vec!["0.002", "0.005", "0.01", "0.02", "0.05", "0.1", "0.2"]
        );
        let l = tick_labels(&nice_ticks(20.05, 20.55, false).0);
        assert_eq!(l, vec!["20.1", "20.2", "20.3", "20.4", "20.5"]);
        let mut dedup = lt.clone();
        dedup.dedup();
        assert_eq!(dedup, lt);
    }

    #[test]
    fn one_point_gets_distinct_ticks() {
        let s = Series {
            label: "a".into(),
            colour: [1.0, 0.0, 0.0],
            points: vec![(200.0, 24.03)],
            line: true,
            marker: 2,
            labels: Vec::new(),
        };
        let f = Frame::fit(&[s], false, 500);
        for (lo, hi, integer, v) in [(f.x0, f.x1, f.integer_x, 200.0), (f.y0, f.y1, false, 24.03)] {
            assert!(lo < v && v < hi, "[{lo}, {hi}] around {v}");
            let ticks = nice_ticks(lo, hi, integer).0;
            let labels = tick_labels(&ticks);
            let mut dedup = labels.clone();
            dedup.dedup();
            assert!(labels.len() >= 2 && dedup == labels, "{labels:?}");
        }
    }

    #[test]
    fn plot_draws_something() {
        let s = Series {
            label: "a".into(),
            colour: [1.0, 0.0, 0.0],
            points: vec![(1.0, 1.0), (2.0, 3.0)],
            line: true,
            marker: 2,
            labels: Vec::new(),
        };
        let img = plot("t", "x", "y", &[s], false);
        assert!(img.data.chunks(3).any(|c| c == [1.0, 0.0, 0.0]));
    }
}
