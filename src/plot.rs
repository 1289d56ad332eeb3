//! Small PNG line and bar charts (training curves, loss curves, histograms,
//! eval summaries) with a built-in 5x7 bitmap font.
//!
//! Written here because the plotting crates render text only through system
//! or bundled TrueType fonts, which a bare CI machine lacks; a chart needs
//! only axes, a few polylines and short labels. Encoding uses the `png`
//! crate.

use anyhow::{Context, Result};
use std::path::Path;

/// One line of a chart.
pub struct Series {
    /// Legend label.
    pub label: String,
    /// (x, y) points; non-finite y values are skipped.
    pub points: Vec<(f64, f64)>,
}

/// A line chart.
pub struct Chart {
    /// Title above the plot.
    pub title: String,
    /// Label under the x axis.
    pub x_label: String,
    /// Label of the y axis (printed above it).
    pub y_label: String,
    /// The lines.
    pub series: Vec<Series>,
    /// Horizontal reference lines (value, label).
    pub hlines: Vec<(f64, String)>,
}

const W: usize = 720;
const H: usize = 420;
const LEFT: usize = 70;
const RIGHT: usize = 20;
const TOP: usize = 40;
const BOTTOM: usize = 50;
const COLORS: [[u8; 3]; 6] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [255, 127, 14],
    [148, 103, 189],
    [140, 86, 75],
];

/// 5x7 glyph rows (bit 4 = leftmost column).
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
        'Y' => [17, 17, 17, 10, 4, 4, 4],
        'Z' => [31, 1, 2, 4, 8, 16, 31],
        '.' => [0, 0, 0, 0, 0, 12, 12],
        ',' => [0, 0, 0, 0, 12, 4, 8],
        '-' => [0, 0, 0, 31, 0, 0, 0],
        '+' => [0, 4, 4, 31, 4, 4, 0],
        '=' => [0, 0, 31, 0, 31, 0, 0],
        ':' => [0, 12, 12, 0, 12, 12, 0],
        '/' => [0, 1, 2, 4, 8, 16, 0],
        '%' => [24, 25, 2, 4, 8, 19, 3],
        '(' => [2, 4, 8, 8, 8, 4, 2],
        ')' => [8, 4, 2, 2, 2, 4, 8],
        '_' => [0, 0, 0, 0, 0, 0, 31],
        '>' => [8, 4, 2, 1, 2, 4, 8],
        '<' => [2, 4, 8, 16, 8, 4, 2],
        _ => [0; 7],
    }
}

struct Canvas {
    px: Vec<u8>,
}

impl Canvas {
    fn new() -> Canvas {
        Canvas {
            px: vec![255; W * H * 3],
        }
    }

    fn set(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as usize) < W && (y as usize) < H {
            let i = 3 * (y as usize * W + x as usize);
            self.px[i..i + 3].copy_from_slice(&c);
        }
    }

    fn line(&mut self, x0: f64, y0: f64, x1: f64, y1: f64, c: [u8; 3], thick: i64) {
        let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
        for k in 0..=n {
            let t = k as f64 / n as f64;
            let (x, y) = (x0 + t * (x1 - x0), y0 + t * (y1 - y0));
            for dx in 0..thick {
                for dy in 0..thick {
                    self.set(x.round() as i64 + dx, y.round() as i64 + dy, c);
                }
            }
        }
    }

    /// Text with its top-left corner at (x, y), `scale` pixels per font dot.
    fn text(&mut self, x: i64, y: i64, s: &str, scale: i64, c: [u8; 3]) {
        for (i, ch) in s.chars().enumerate() {
            let g = glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (1 << (4 - col)) != 0 {
                        for sx in 0..scale {
                            for sy in 0..scale {
                                self.set(
                                    x + (i as i64 * 6 + col) * scale + sx,
                                    y + row as i64 * scale + sy,
                                    c,
                                );
                            }
                        }
                    }
                }
            }
        }
    }
}

fn text_width(s: &str, scale: i64) -> i64 {
    s.chars().count() as i64 * 6 * scale
}

/// "Nice" tick step for a range.
fn tick_step(span: f64, ticks: f64) -> f64 {
    let raw = (span / ticks).max(1e-12);
    let mag = 10f64.powf(raw.log10().floor());
    let f = raw / mag;
    let nice = if f < 1.5 {
        1.0
    } else if f < 3.0 {
        2.0
    } else if f < 7.0 {
        5.0
    } else {
        10.0
    };
    nice * mag
}

fn label(v: f64, step: f64) -> String {
    if step >= 1e5 {
        format!("{:.1}M", v / 1e6)
    } else if step >= 1.0 {
        format!("{v:.0}")
    } else {
        let d = (-step.log10().floor()) as usize;
        format!("{v:.d$}")
    }
}

/// Render `chart` as a PNG at `path` (written to a temporary file, then renamed).
pub fn write_png(chart: &Chart, path: &Path) -> Result<()> {
    let pts = chart
        .series
        .iter()
        .flat_map(|s| s.points.iter())
        .filter(|p| p.1.is_finite());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    for (v, _) in &chart.hlines {
        y0 = y0.min(*v);
        y1 = y1.max(*v);
    }
    if x0 > x1 {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    y0 = y0.min(0.0);
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    if y1 <= y0 {
        y1 = y0 + 1.0;
    }
    let ys = tick_step(y1 - y0, 5.0);
    y1 = (y1 / ys).ceil() * ys;
    let xs = tick_step(x1 - x0, 6.0);
    let (pw, ph) = ((W - LEFT - RIGHT) as f64, (H - TOP - BOTTOM) as f64);
    let px = |x: f64| LEFT as f64 + (x - x0) / (x1 - x0) * pw;
    let py = |y: f64| TOP as f64 + (1.0 - (y - y0) / (y1 - y0)) * ph;
    let mut c = Canvas::new();
    let black = [30, 30, 30];
    c.y_grid(y0, y1, ys, py);
    let mut t = (x0 / xs).ceil() * xs;
    while t <= x1 + 1e-9 {
        c.line(px(t), py(y0), px(t), py(y0) + 4.0, black, 1);
        let l = label(t, xs);
        c.text(
            px(t) as i64 - text_width(&l, 1) / 2,
            (H - BOTTOM) as i64 + 8,
            &l,
            1,
            black,
        );
        t += xs;
    }
    c.line(px(x0), py(y0), px(x1), py(y0), black, 1);
    c.line(px(x0), py(y0), px(x0), py(y1), black, 1);
    for (v, l) in &chart.hlines {
        let mut x = px(x0);
        while x < px(x1) {
            c.line(x, py(*v), (x + 6.0).min(px(x1)), py(*v), [120, 120, 120], 1);
            x += 12.0;
        }
        c.text(
            px(x1) as i64 - text_width(l, 1) - 4,
            py(*v) as i64 - 10,
            l,
            1,
            [90, 90, 90],
        );
    }
    for (k, s) in chart.series.iter().enumerate() {
        let col = COLORS[k % COLORS.len()];
        let p: Vec<(f64, f64)> = s
            .points
            .iter()
            .copied()
            .filter(|p| p.1.is_finite())
            .collect();
        for w in p.windows(2) {
            c.line(px(w[0].0), py(w[0].1), px(w[1].0), py(w[1].1), col, 2);
        }
        let ly = TOP as i64 + 6 + 14 * k as i64;
        c.line(
            LEFT as f64 + 10.0,
            ly as f64 + 3.0,
            LEFT as f64 + 30.0,
            ly as f64 + 3.0,
            col,
            2,
        );
        c.text(LEFT as i64 + 36, ly, &s.label, 1, black);
    }
    c.labels(&chart.title, &chart.x_label, &chart.y_label);
    c.write(path)
}

impl Canvas {
    /// Encode as PNG at `path` (staged, then moved into place:
    /// [`crate::table::io::Staged`]).
    fn write(&self, path: &Path) -> Result<()> {
        let mut staged = crate::table::io::Staged::new();
        staged.with_path(path, |tmp| {
            let f = std::fs::File::create(tmp)
                .with_context(|| format!("cannot write {}", path.display()))?;
            let mut enc = png::Encoder::new(std::io::BufWriter::new(f), W as u32, H as u32);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut wr = enc.write_header()?;
            wr.write_image_data(&self.px)?;
            wr.finish()?;
            Ok(())
        })?;
        staged.commit()
    }

    /// Text read bottom to top (turned a quarter left), its first letter's
    /// left edge at `top` + the text's length: the text hangs from `top`.
    fn text_up(&mut self, x: i64, top: i64, s: &str, c: [u8; 3]) {
        let len = s.chars().count() as i64 * 6;
        for (i, ch) in s.chars().enumerate() {
            let g = glyph(ch);
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (1 << (4 - col)) != 0 {
                        // glyph (col, row) -> (x + row, top + len - (i*6 + col))
                        self.set(x + row as i64, top + len - (i as i64 * 6 + col), c);
                    }
                }
            }
        }
    }

    /// Filled rectangle between pixel corners.
    fn rect(&mut self, x0: f64, y0: f64, x1: f64, y1: f64, c: [u8; 3]) {
        let (xa, xb) = (x0.min(x1).round() as i64, x0.max(x1).round() as i64);
        let (ya, yb) = (y0.min(y1).round() as i64, y0.max(y1).round() as i64);
        for y in ya..=yb {
            for x in xa..=xb {
                self.set(x, y, c);
            }
        }
    }

    /// Title centred on top, x label under the plot, y label above the axis.
    fn labels(&mut self, title: &str, x_label: &str, y_label: &str) {
        let black = [30, 30, 30];
        self.text((W as i64 - text_width(title, 2)) / 2, 10, title, 2, black);
        self.text(
            (W as i64 - text_width(x_label, 1)) / 2,
            H as i64 - 14,
            x_label,
            1,
            black,
        );
        self.text(6, TOP as i64 - 14, y_label, 1, black);
    }

    /// Horizontal grid lines with tick labels on the y axis from `y0` to
    /// `y1` (in steps of `ys`), mapped by `py`.
    fn y_grid(&mut self, y0: f64, y1: f64, ys: f64, py: impl Fn(f64) -> f64) {
        let mut t = (y0 / ys).ceil() * ys;
        while t <= y1 + 1e-9 {
            self.line(
                LEFT as f64,
                py(t),
                (W - RIGHT) as f64,
                py(t),
                [210, 210, 210],
                1,
            );
            let l = label(t, ys);
            self.text(
                LEFT as i64 - 6 - text_width(&l, 1),
                py(t) as i64 - 3,
                &l,
                1,
                [30, 30, 30],
            );
            t += ys;
        }
    }
}

/// A grouped bar chart: one group per category, one bar per series.
pub struct BarChart {
    /// Title above the plot.
    pub title: String,
    /// Label under the categories.
    pub x_label: String,
    /// Label of the y axis.
    pub y_label: String,
    /// Category names, left to right.
    pub categories: Vec<String>,
    /// Series: label and, per category, the value and an optional interval.
    pub series: Vec<BarSeries>,
}

/// One series of a [`BarChart`].
pub struct BarSeries {
    /// Legend label.
    pub label: String,
    /// Per category: value (NaN: no bar) and optional (low, high) whiskers.
    pub values: Vec<(f64, Option<(f64, f64)>)>,
}

/// Render a bar chart as a PNG at `path`. Category labels are cut to the
/// width of their group.
pub fn write_bars_png(chart: &BarChart, path: &Path) -> Result<()> {
    let nc = chart.categories.len().max(1);
    let ns = chart.series.len().max(1);
    let mut y1 = 0f64;
    for s in &chart.series {
        for (v, iv) in &s.values {
            if v.is_finite() {
                y1 = y1.max(*v);
            }
            if let Some((_, hi)) = iv {
                if hi.is_finite() {
                    y1 = y1.max(*hi);
                }
            }
        }
    }
    if y1 <= 0.0 {
        y1 = 1.0;
    }
    let ys = tick_step(y1, 5.0);
    y1 = (y1 / ys).ceil() * ys;
    let gw = (W - LEFT - RIGHT) as f64 / nc as f64;
    // category names that do not fit under their group are written upwards
    // in a taller bottom margin
    let longest = chart
        .categories
        .iter()
        .map(|c| c.chars().count())
        .max()
        .unwrap_or(0);
    let upright = text_width(&"x".repeat(longest), 1) as f64 > gw - 2.0;
    let bottom = if upright {
        (longest * 6 + 30).clamp(BOTTOM, 150)
    } else {
        BOTTOM
    };
    let ph = (H - TOP - bottom) as f64;
    let py = |y: f64| TOP as f64 + (1.0 - y / y1) * ph;
    let mut c = Canvas::new();
    c.y_grid(0.0, y1, ys, py);
    let black = [30, 30, 30];
    let bw = (gw * 0.8 / ns as f64).max(1.0);
    for (k, cat) in chart.categories.iter().enumerate() {
        let gx = LEFT as f64 + k as f64 * gw;
        for (j, s) in chart.series.iter().enumerate() {
            let Some(&(v, iv)) = s.values.get(k) else {
                continue;
            };
            let x0 = gx + gw * 0.1 + j as f64 * bw;
            if v.is_finite() {
                c.rect(
                    x0,
                    py(0.0),
                    x0 + bw - 2.0,
                    py(v.max(0.0)),
                    COLORS[j % COLORS.len()],
                );
            }
            if let Some((lo, hi)) = iv.filter(|(a, b)| a.is_finite() && b.is_finite()) {
                let xm = x0 + bw / 2.0 - 1.0;
                c.line(xm, py(lo), xm, py(hi), black, 1);
                c.line(xm - 3.0, py(lo), xm + 3.0, py(lo), black, 1);
                c.line(xm - 3.0, py(hi), xm + 3.0, py(hi), black, 1);
            }
        }
        if upright {
            let fit = (bottom - 30) / 6;
            let l: String = cat.chars().take(fit).collect();
            c.text_up(
                (gx + gw / 2.0) as i64 - 3,
                (H - bottom) as i64 + 6,
                &l,
                black,
            );
        } else {
            c.text(
                (gx + gw / 2.0) as i64 - text_width(cat, 1) / 2,
                (H - bottom) as i64 + 8,
                cat,
                1,
                black,
            );
        }
    }
    c.line(LEFT as f64, py(0.0), (W - RIGHT) as f64, py(0.0), black, 1);
    c.line(LEFT as f64, py(0.0), LEFT as f64, py(y1), black, 1);
    if chart.series.len() > 1 || chart.series.iter().any(|s| !s.label.is_empty()) {
        for (j, s) in chart.series.iter().enumerate() {
            let ly = TOP as i64 + 6 + 14 * j as i64;
            let x = (W - RIGHT) as i64 - 20 - text_width(&s.label, 1);
            c.rect(
                x as f64 - 16.0,
                ly as f64,
                x as f64 - 6.0,
                ly as f64 + 6.0,
                COLORS[j % COLORS.len()],
            );
            c.text(x, ly, &s.label, 1, black);
        }
    }
    c.labels(&chart.title, &chart.x_label, &chart.y_label);
    c.write(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_chart_is_written_and_not_blank() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.png");
        let chart = Chart {
            title: "Test".into(),
            x_label: "samples".into(),
            y_label: "reward".into(),
            series: vec![Series {
                label: "a".into(),
                points: (0..50)
                    .map(|i| (i as f64 * 1e4, (i as f64 / 10.0).sin()))
                    .collect(),
            }],
            hlines: vec![(0.5, "goal".into())],
        };
        write_png(&chart, &p).unwrap();
        let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&p).unwrap()));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (W as u32, H as u32));
        let coloured = buf[..info.buffer_size()]
            .chunks_exact(3)
            .filter(|p| p[0] == COLORS[0][0] && p[1] == COLORS[0][1] && p[2] == COLORS[0][2])
            .count();
        assert!(coloured > 200, "{coloured} line pixels");
    }

    #[test]
    fn ticks_are_round_numbers() {
        assert_eq!(tick_step(1.0, 5.0), 0.2);
        assert_eq!(tick_step(2e6, 6.0), 5e5);
        assert_eq!(label(0.2, 0.05), "0.20");
        assert_eq!(label(1.5e6, 5e5), "1.5M");
    }
}
