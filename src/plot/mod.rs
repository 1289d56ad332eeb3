//! PNG line and bar charts (training curves, loss curves, histograms, eval
//! summaries), drawn with `plotters` on its bitmap backend.
//!
//! Text uses DejaVu Sans from the `dejavu` crate, registered with plotters'
//! `ab_glyph` font backend, so a machine without system fonts (a bare CI
//! machine) draws the same labels. The pixels are encoded with the `png`
//! crate and written through [`crate::table::io::Staged`] (temporary file,
//! then rename), like every other output.

pub mod figures;

use anyhow::{anyhow, Context, Result};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::FontTransform;
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
    /// Label of the y axis (printed beside it, read bottom to top).
    pub y_label: String,
    /// The lines.
    pub series: Vec<Series>,
    /// Horizontal reference lines (value, label).
    pub hlines: Vec<(f64, String)>,
}

/// Image size, pixels.
const W: u32 = 720;
const H: u32 = 420;
const COLORS: [[u8; 3]; 6] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [255, 127, 14],
    [148, 103, 189],
    [140, 86, 75],
];
const INK: RGBColor = RGBColor(30, 30, 30);
const FONT: &str = "sans-serif";

fn color(k: usize) -> RGBColor {
    let [r, g, b] = COLORS[k % COLORS.len()];
    RGBColor(r, g, b)
}

/// Register the embedded font once per process.
fn font() -> Result<()> {
    static REGISTERED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(anyhow!("the embedded DejaVu Sans font could not be parsed"))
    }
}

fn text(size: f64) -> TextStyle<'static> {
    TextStyle::from((FONT, size).into_font()).color(&INK)
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

/// Number of ticks of step `step` from the first multiple at or above `lo`
/// to `hi`.
fn n_ticks(lo: f64, hi: f64, step: f64) -> usize {
    (((hi - lo) / step).floor() as usize + 2).min(50)
}

/// Draw with `draw` on a white `W` x `H` bitmap and write it as a PNG at
/// `path`.
fn render(
    path: &Path,
    draw: impl FnOnce(&DrawingArea<BitMapBackend, Shift>) -> Result<()>,
) -> Result<()> {
    font()?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        // as `view` does: a missing folder is made, not reported as a
        // failure to create the temporary file inside it
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the folder of {}", path.display()))?;
    }
    let mut px = vec![255u8; (W * H * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut px, (W, H)).into_drawing_area();
        draw(&root).with_context(|| format!("cannot draw {}", path.display()))?;
        root.present()
            .map_err(|e| anyhow!("cannot draw {}: {e}", path.display()))?;
    }
    let mut staged = crate::table::io::Staged::new();
    staged.with_path(path, |tmp| {
        let f = std::fs::File::create(tmp)
            .with_context(|| format!("cannot write {}", path.display()))?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(f), W, H);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header()?;
        wr.write_image_data(&px)?;
        wr.finish()?;
        Ok(())
    })?;
    staged.commit()
}

fn drawing<E: std::error::Error + Send + Sync + 'static>(
    e: DrawingAreaErrorKind<E>,
) -> anyhow::Error {
    anyhow!("{e}")
}

/// A chart's plot area, in f64 data coordinates on both axes.
type Plane<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// The plot area of both chart kinds on `root`: `title` on top, `x_area`
/// pixels under the plot for the x labels, 64 beside it for the y labels.
fn plane<'a, 'b>(
    root: &'a DrawingArea<BitMapBackend<'b>, Shift>,
    title: &str,
    x_area: u32,
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
) -> Result<Plane<'a, 'b>> {
    ChartBuilder::on(root)
        .caption(title, text(22.0))
        .margin(12)
        .x_label_area_size(x_area)
        .y_label_area_size(64)
        .build_cartesian_2d(x, y)
        .map_err(drawing)
}

/// An axis of [`draw_mesh`]: its description, number of labels and their
/// text.
type Axis<'f> = (&'f str, usize, &'f dyn Fn(&f64) -> String);

/// Axes, horizontal grid lines at the y labels and the axis descriptions,
/// in the style of every chart here.
fn draw_mesh(ch: &mut Plane, x: Axis, y: Axis) -> Result<()> {
    ch.configure_mesh()
        .disable_x_mesh()
        .x_labels(x.1)
        .y_labels(y.1)
        .x_label_formatter(x.2)
        .y_label_formatter(y.2)
        .x_desc(x.0)
        .y_desc(y.0)
        .label_style(text(13.0))
        .axis_desc_style(text(14.0))
        .bold_line_style(RGBColor(210, 210, 210))
        .light_line_style(TRANSPARENT)
        .axis_style(INK)
        .draw()
        .map_err(drawing)
}

/// The legend of the series drawn with labels, at `at`.
fn draw_legend<'a, 'b: 'a>(ch: &mut Plane<'a, 'b>, at: SeriesLabelPosition) -> Result<()> {
    ch.configure_series_labels()
        .position(at)
        .label_font(text(13.0))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(210, 210, 210))
        .draw()
        .map_err(drawing)
}

/// Render `chart` as a PNG at `path` (written to a temporary file, then
/// renamed). The y axis always includes 0; dashed grey lines mark `hlines`.
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
    render(path, |root| {
        root.fill(&WHITE).map_err(drawing)?;
        let mut ch = plane(root, &chart.title, 42, x0..x1, y0..y1)?;
        draw_mesh(
            &mut ch,
            (&chart.x_label, n_ticks(x0, x1, xs), &|v| label(*v, xs)),
            (&chart.y_label, n_ticks(y0, y1, ys), &|v| label(*v, ys)),
        )?;
        let grey = RGBColor(120, 120, 120);
        for (v, l) in &chart.hlines {
            ch.draw_series(DashedLineSeries::new(
                [(x0, *v), (x1, *v)],
                6,
                6,
                grey.into(),
            ))
            .map_err(drawing)?;
            let at = ch.backend_coord(&(x1, *v));
            root.draw(&Text::new(
                l.clone(),
                (at.0 - 4, at.1 - 4),
                text(13.0)
                    .color(&RGBColor(90, 90, 90))
                    .pos(Pos::new(HPos::Right, VPos::Bottom)),
            ))
            .map_err(drawing)?;
        }
        for (k, s) in chart.series.iter().enumerate() {
            let col = color(k);
            let p: Vec<(f64, f64)> = s
                .points
                .iter()
                .copied()
                .filter(|p| p.1.is_finite())
                .collect();
            ch.draw_series(LineSeries::new(p, col.stroke_width(2)))
                .map_err(drawing)?
                .label(s.label.as_str())
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], col.stroke_width(2)));
        }
        if !chart.series.is_empty() {
            draw_legend(&mut ch, SeriesLabelPosition::UpperLeft)?;
        }
        Ok(())
    })
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

/// Render a bar chart as a PNG at `path`. Category names that do not fit
/// under their group are written upwards in a taller bottom margin and cut
/// to its height.
pub fn write_bars_png(chart: &BarChart, path: &Path) -> Result<()> {
    let nc = chart.categories.len().max(1);
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
    render(path, |root| {
        root.fill(&WHITE).map_err(drawing)?;
        let small = text(13.0);
        let widest = chart
            .categories
            .iter()
            .map(|c| root.estimate_text_size(c, &small).map_or(0, |s| s.0))
            .max()
            .unwrap_or(0);
        let group_px = (W as f64 - 12.0 - 64.0 - 12.0) / nc as f64;
        let upright = widest as f64 > group_px - 4.0;
        let bottom = if upright {
            (widest + 30).clamp(42, 150)
        } else {
            42
        };
        let mut ch = plane(root, &chart.title, bottom, 0f64..nc as f64, 0f64..y1)?;
        // no x labels: the category names are drawn under their groups
        draw_mesh(
            &mut ch,
            (&chart.x_label, 0, &|v| label(*v, 1.0)),
            (&chart.y_label, n_ticks(0.0, y1, ys), &|v| label(*v, ys)),
        )?;
        let ns = chart.series.len().max(1);
        let bw = 0.8 / ns as f64;
        for (j, s) in chart.series.iter().enumerate() {
            let col = color(j);
            let bars = s
                .values
                .iter()
                .take(nc)
                .enumerate()
                .filter_map(|(k, (v, _))| {
                    let x = k as f64 + 0.1 + j as f64 * bw;
                    v.is_finite().then(|| {
                        Rectangle::new([(x, 0.0), (x + bw * 0.9, v.max(0.0))], col.filled())
                    })
                });
            let drawn = ch.draw_series(bars).map_err(drawing)?;
            if ns > 1 || !s.label.is_empty() {
                drawn.label(s.label.as_str()).legend(move |(x, y)| {
                    Rectangle::new([(x, y - 4), (x + 10, y + 4)], col.filled())
                });
            }
            let whiskers = s
                .values
                .iter()
                .take(nc)
                .enumerate()
                .filter_map(|(k, (_, iv))| {
                    let (lo, hi) = iv.filter(|(a, b)| a.is_finite() && b.is_finite())?;
                    let xm = k as f64 + 0.1 + (j as f64 + 0.45) * bw;
                    let cap = 0.15 * bw;
                    Some(
                        [
                            [(xm, lo), (xm, hi)],
                            [(xm - cap, lo), (xm + cap, lo)],
                            [(xm - cap, hi), (xm + cap, hi)],
                        ]
                        .map(|l| PathElement::new(l, INK)),
                    )
                });
            ch.draw_series(whiskers.flatten()).map_err(drawing)?;
        }
        for (k, cat) in chart.categories.iter().enumerate() {
            let (x, y) = ch.backend_coord(&(k as f64 + 0.5, 0.0));
            let style = if upright {
                small
                    .transform(FontTransform::Rotate270)
                    .pos(Pos::new(HPos::Right, VPos::Center))
            } else {
                small.pos(Pos::new(HPos::Center, VPos::Top))
            };
            let fit: String = if upright {
                let mut s = cat.clone();
                while s.chars().count() > 1
                    && root.estimate_text_size(&s, &small).map_or(0, |t| t.0) > bottom - 30
                {
                    s.pop();
                }
                s
            } else {
                cat.clone()
            };
            root.draw(&Text::new(fit, (x, y + 6), style))
                .map_err(drawing)?;
        }
        if chart.series.len() > 1 || chart.series.iter().any(|s| !s.label.is_empty()) {
            draw_legend(&mut ch, SeriesLabelPosition::UpperRight)?;
        }
        Ok(())
    })
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
        assert_eq!((info.width, info.height), (W, H));
        let coloured = buf[..info.buffer_size()]
            .chunks_exact(3)
            .filter(|p| p[0] == COLORS[0][0] && p[1] == COLORS[0][1] && p[2] == COLORS[0][2])
            .count();
        assert!(coloured > 200, "{coloured} line pixels");
    }

    fn decode(p: &Path) -> Vec<u8> {
        let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (W, H));
        buf.truncate(info.buffer_size());
        buf
    }

    #[test]
    fn long_category_names_are_written_upwards_below_the_bars() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.png");
        let chart = BarChart {
            title: "Bars".into(),
            x_label: "cell".into(),
            y_label: "SR".into(),
            categories: (0..8)
                .map(|i| format!("sr 013_018pickle_run_{i} and more"))
                .collect(),
            series: vec![BarSeries {
                label: "SM".into(),
                values: (0..8)
                    .map(|i| ((i + 1) as f64 / 10.0, Some((0.0, 0.9))))
                    .collect(),
            }],
        };
        write_bars_png(&chart, &p).unwrap();
        let px = decode(&p);
        let row_ink = |y: u32| {
            px[(y * W * 3) as usize..((y + 1) * W * 3) as usize]
                .chunks_exact(3)
                .filter(|c| c[0] < 160 && c[1] < 160 && c[2] < 160)
                .count()
        };
        let bars = px.chunks_exact(3).filter(|c| c == &COLORS[0]).count();
        assert!(bars > 2000, "{bars} bar pixels");
        // the upright names fill a tall band under the plot: ink in the
        // rows of their letters (60 of these 90 rows when measured; the
        // gaps between letters are blank), where level names 13 px high
        // would ink at most 13 rows
        let band = (H - 130..H - 40).filter(|y| row_ink(*y) >= 4).count();
        assert!(band > 40, "{band} of 90 rows carry text");
    }

    #[test]
    fn ticks_are_round_numbers() {
        assert_eq!(tick_step(1.0, 5.0), 0.2);
        assert_eq!(tick_step(2e6, 6.0), 5e5);
        assert_eq!(label(0.2, 0.05), "0.20");
        assert_eq!(label(1.5e6, 5e5), "1.5M");
    }
}
