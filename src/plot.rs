//! Small PNG line charts (training curves) with a built-in 5x7 bitmap font.
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
    let grey = [210, 210, 210];
    let black = [30, 30, 30];
    let mut t = (y0 / ys).ceil() * ys;
    while t <= y1 + 1e-9 {
        c.line(px(x0), py(t), px(x1), py(t), grey, 1);
        let l = label(t, ys);
        c.text(
            LEFT as i64 - 6 - text_width(&l, 1),
            py(t) as i64 - 3,
            &l,
            1,
            black,
        );
        t += ys;
    }
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
    c.text(
        (W as i64 - text_width(&chart.title, 2)) / 2,
        10,
        &chart.title,
        2,
        black,
    );
    c.text(
        (W as i64 - text_width(&chart.x_label, 1)) / 2,
        H as i64 - 20,
        &chart.x_label,
        1,
        black,
    );
    c.text(6, TOP as i64 - 14, &chart.y_label, 1, black);

    let tmp = path.with_extension("png.tmp");
    {
        let f = std::fs::File::create(&tmp)
            .with_context(|| format!("cannot write {}", tmp.display()))?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(f), W as u32, H as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header()?;
        wr.write_image_data(&c.px)?;
    }
    std::fs::rename(&tmp, path)?;
    Ok(())
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
