//! PNG figures with plotters: grouped points with error bars, lines with bands, scatters.
//! The font (DejaVu Sans) is bundled, so figures render the same on any machine.
//! Each figure is drawn to a temporary file and renamed into place.

use plotters::coord::ranged1d::{KeyPointHint, NoDefaultFormatting, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Once;

/// Where a figure's legend goes (plotters' type, re-exported for the figures' callers).
pub use plotters::chart::SeriesLabelPosition;

#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error("drawing {path}: {reason}")]
    Draw {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("writing {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

static FONT: Once = Once::new();

pub(crate) fn register_font() {
    FONT.call_once(|| {
        // The bytes are ours and valid; a failure here would only mean missing text.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../assets/fonts/DejaVuSans.ttf"),
        );
    });
}

/// Distinct, colour-blind-friendly series colours (Okabe–Ito).
pub const PALETTE: [RGBColor; 6] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
];

/// The committed models (`checkpoints/`, `scripts/results.sh`) in the order the docs list them:
/// their colour slots in every figure, with [`colour_slots`].
pub const MODEL_COLOURS: [&str; 4] = [
    "baseline",
    "encoder-lstm",
    "encoder-mlp",
    "encoder-lstm-aux",
];

/// Palette slots for series keys: a key listed in `fixed` takes its index there (so one model
/// has one colour in every figure), any other key the lowest slot no key of this figure holds,
/// in order of first appearance; equal keys share a slot.
pub fn colour_slots(keys: &[&str], fixed: &[&str]) -> Vec<usize> {
    let mut taken: Vec<usize> = keys
        .iter()
        .filter_map(|k| fixed.iter().position(|f| f == k))
        .collect();
    let mut assigned: Vec<(&str, usize)> = Vec::new();
    keys.iter()
        .map(|&key| {
            if let Some(slot) = fixed.iter().position(|f| *f == key) {
                return slot;
            }
            if let Some(&(_, slot)) = assigned.iter().find(|(k, _)| *k == key) {
                return slot;
            }
            let slot = (0..)
                .find(|s| !taken.contains(s))
                .expect("an unbounded range has a free slot");
            taken.push(slot);
            assigned.push((key, slot));
            slot
        })
        .collect()
}

fn palette(slot: usize) -> RGBColor {
    PALETTE[slot % PALETTE.len()]
}

/// Renders with `draw` into `path` via a temp file + rename.
pub fn render(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(
        &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    ) -> Result<(), Box<dyn std::error::Error>>,
) -> Result<(), PlotError> {
    register_font();
    let file_name = path
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("figure");
    let tmp = path.with_file_name(format!(".{file_name}.tmp.png"));
    let fail = |reason: String| PlotError::Draw {
        path: path.to_owned(),
        reason: reason.into(),
    };
    {
        let root = BitMapBackend::new(&tmp, size).into_drawing_area();
        root.fill(&WHITE).map_err(|e| fail(e.to_string()))?;
        draw(&root).map_err(|e| fail(e.to_string()))?;
        root.present().map_err(|e| fail(e.to_string()))?;
    }
    std::fs::rename(&tmp, path).map_err(|source| PlotError::Io {
        path: path.to_owned(),
        source,
    })
}

/// One series of a grouped error-bar chart: a value and interval per category.
pub struct ErrorBarSeries {
    pub label: String,
    /// Palette slot ([`colour_slots`]).
    pub colour: usize,
    /// Whether `label` gets a legend entry (one per colour when several series share one).
    pub in_legend: bool,
    /// (value, low, high) per category.
    pub points: Vec<(f64, f64, f64)>,
    /// Values drawn as small open circles beside each point (e.g. one per training seed);
    /// empty for none.
    pub dots: Vec<Vec<f64>>,
}

/// Room above the data for the legend, as a fraction of the data's range.
const LEGEND_HEADROOM: f64 = 0.3;

/// A tick's label on an axis spanning `span`: whole numbers from a span of 20 up (percentages,
/// returns, steps: "700", not "700.0"), below that the decimals a tenth of the span needs.
fn tick_label(value: f64, span: f64) -> String {
    let decimals = if span >= 20.0 || !span.is_finite() || span <= 0.0 {
        0
    } else {
        (-(span / 10.0).log10()).ceil().clamp(0.0, 6.0) as usize
    };
    // No "-0": a tick at zero reads 0 from either side.
    let value = if value.abs() < 0.5 * 10f64.powi(-(decimals as i32)) {
        0.0
    } else {
        value
    };
    format!("{value:.decimals$}")
}

/// An error-bar chart's y ticks: round steps (1, 2 or 5 × 10^k, at most six of them) over the
/// values' range only, and four light grid lines inside each step. The legend's headroom above
/// the range gets neither: it is not a value, and a tick there would read as one.
/// Also the decimals a label needs at that step (2 m steps read "2", half metres "2.5").
fn y_key_points((bottom, top): (f64, f64)) -> (Vec<f64>, Vec<f64>, usize) {
    let span = top - bottom;
    if !(span.is_finite() && span > 0.0) {
        return (vec![bottom], Vec::new(), 0);
    }
    let magnitude = 10f64.powf((span / 5.0).log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * magnitude)
        .find(|s| span / s <= 6.0)
        .unwrap_or(10.0 * magnitude);
    let eps = 1e-9 * span;
    let points = |step: f64| -> Vec<f64> {
        let first = (bottom / step - 1e-9).ceil() as i64;
        (first..)
            .map(|k| k as f64 * step)
            .take_while(|v| *v <= top + eps)
            .collect()
    };
    let bold = points(step);
    let light = points(step / 5.0)
        .into_iter()
        .filter(|v| bold.iter().all(|b| (b - v).abs() > eps))
        .collect();
    let decimals = (-(step.log10() + 1e-9).floor()).clamp(0.0, 9.0) as usize;
    (bold, light, decimals)
}

/// A value axis with the ticks given ([`y_key_points`]): plotters' own `WithKeyPoints` has no
/// number format for `f64`, so the mesh will not draw it.
struct TickedAxis {
    range: RangedCoordf64,
    bold: Vec<f64>,
    light: Vec<f64>,
}

impl Ranged for TickedAxis {
    type ValueType = f64;
    type FormatOption = NoDefaultFormatting;

    fn range(&self) -> std::ops::Range<f64> {
        self.range.range()
    }

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        self.range.map(value, limit)
    }

    fn key_points<Hint: KeyPointHint>(&self, hint: Hint) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            self.light.clone()
        } else {
            self.bold.clone()
        }
    }
}

impl ValueFormatter<f64> for TickedAxis {
    fn format(value: &f64) -> String {
        value.to_string()
    }
}

/// Points with error bars, grouped by category, side by side within each in series order, on
/// `y_range` (the values' range: the chart adds room above it for the legend).
pub fn error_bars(
    path: &Path,
    title: &str,
    y_label: &str,
    categories: &[&str],
    series: &[ErrorBarSeries],
    y_range: (f64, f64),
) -> Result<(), PlotError> {
    let y_top = y_range.1 + LEGEND_HEADROOM * (y_range.1 - y_range.0);
    // At least ~9 px per point, so many runs over many categories stay apart.
    let width = (120 + 9 * categories.len() * series.len()).max(900) as u32;
    render(path, (width, 560), |root| {
        let n = series.len().max(1) as f64;
        let (bold, light, decimals) = y_key_points(y_range);
        let y_axis = TickedAxis {
            range: (y_range.0..y_top).into(),
            bold,
            light,
        };
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 26))
            .margin(16)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(-0.5f64..categories.len() as f64 - 0.5, y_axis)?;
        chart
            .configure_mesh()
            .y_desc(y_label)
            .y_label_formatter(&|y| format!("{:.decimals$}", y + 0.0))
            .x_labels(categories.len())
            .x_label_formatter(&|x| {
                let i = x.round() as i64;
                if (x - i as f64).abs() < 1e-6 && i >= 0 {
                    categories
                        .get(i as usize)
                        .map(|s| s.to_string())
                        .unwrap_or_default()
                } else {
                    String::new()
                }
            })
            .disable_x_mesh()
            .label_style(("sans-serif", 16))
            .draw()?;
        // The series of one category spread over at most 0.84 of the gap between categories.
        let spacing = (0.84 / n).min(0.12);
        let (whisker, radius) = if spacing < 0.06 { (6, 3) } else { (12, 5) };
        for (s, ser) in series.iter().enumerate() {
            let color = palette(ser.colour);
            let offset = (s as f64 - (n - 1.0) / 2.0) * spacing;
            let bars =
                chart.draw_series(ser.points.iter().enumerate().map(|(c, &(v, lo, hi))| {
                    ErrorBar::new_vertical(
                        c as f64 + offset,
                        lo,
                        v,
                        hi,
                        color.filled().stroke_width(2),
                        whisker,
                    )
                }))?;
            if ser.in_legend {
                bars.label(ser.label.clone())
                    .legend(move |(x, y)| Circle::new((x + 10, y), 5, color.filled()));
            }
            chart.draw_series(ser.points.iter().enumerate().map(|(c, &(v, _, _))| {
                Circle::new((c as f64 + offset, v), radius, color.filled())
            }))?;
            chart.draw_series(ser.dots.iter().enumerate().flat_map(|(c, values)| {
                values.iter().map(move |&v| {
                    Circle::new(
                        (c as f64 + offset + 0.3 * spacing, v),
                        3,
                        color.stroke_width(1),
                    )
                })
            }))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 16))
            .draw()?;
        Ok(())
    })
}

/// One stacked bar: its label and its segments' heights, bottom first.
pub struct StackedBar {
    pub label: String,
    pub segments: Vec<f64>,
}

/// One panel of stacked bars (one model's conditions), titled.
pub struct BarPanel {
    pub title: String,
    pub bars: Vec<StackedBar>,
}

const BAR_LABEL_PX: f64 = 13.0;
const BAR_CHART_MARGIN: u32 = 12;
const BAR_CHART_Y_LABELS: u32 = 56;
/// Space between two neighbouring bar labels.
const BAR_LABEL_GAP: u32 = 16;
const BAR_FIGURE_WIDTH: u32 = 1200;
const BAR_TITLE_HEIGHT: u32 = 40;
const BAR_LEGEND_HEIGHT: u32 = 30;
const BAR_PANEL_HEIGHT: u32 = 260;

/// Where the panels of a stacked-bar figure go.
#[derive(Debug, PartialEq)]
struct BarLayout {
    cols: usize,
    rows: usize,
    width: u32,
    height: u32,
}

/// Panels side by side while they fit 1200 px, else in rows, each panel wide enough that every
/// bar's slot holds its widest label (measured in the bundled font) and a gap, so no two labels
/// run together (twelve "model condition" labels in one 1200-px row did).
fn bar_layout(panels: &[BarPanel]) -> BarLayout {
    register_font();
    let font = ("sans-serif", BAR_LABEL_PX).into_font();
    let slot = panels
        .iter()
        .flat_map(|p| &p.bars)
        .map(|b| font.box_size(&b.label).map_or(0, |(w, _)| w))
        .max()
        .unwrap_or(0)
        + BAR_LABEL_GAP;
    let most_bars = panels.iter().map(|p| p.bars.len()).max().unwrap_or(0) as u32;
    let panel_width = most_bars * slot + 2 * BAR_CHART_MARGIN + BAR_CHART_Y_LABELS;
    let cols = ((BAR_FIGURE_WIDTH / panel_width.max(1)) as usize).clamp(1, panels.len().max(1));
    let rows = panels.len().div_ceil(cols).max(1);
    BarLayout {
        cols,
        rows,
        width: BAR_FIGURE_WIDTH.max(cols as u32 * panel_width),
        height: BAR_TITLE_HEIGHT + BAR_LEGEND_HEIGHT + rows as u32 * BAR_PANEL_HEIGHT,
    }
}

/// Stacked bars, one panel per group (a model), one colour per segment kind; the legend is a
/// row under the title, so it never covers a bar.
pub fn stacked_bars(
    path: &Path,
    title: &str,
    y_label: &str,
    segment_names: &[&str],
    panels: &[BarPanel],
) -> Result<(), PlotError> {
    let top = panels
        .iter()
        .flat_map(|p| &p.bars)
        .map(|b| b.segments.iter().sum::<f64>())
        .fold(0.0f64, f64::max)
        .max(1e-9);
    let layout = bar_layout(panels);
    render(path, (layout.width, layout.height), |root| {
        let body = root.titled(title, ("sans-serif", 24))?;
        let (legend, grid) = body.split_vertically(BAR_LEGEND_HEIGHT);
        let key_font = ("sans-serif", 14).into_font();
        let mut x = BAR_CHART_Y_LABELS as i32;
        for (k, name) in segment_names.iter().enumerate() {
            let color = PALETTE[k % PALETTE.len()];
            legend.draw(&Rectangle::new([(x, 8), (x + 14, 22)], color.filled()))?;
            legend.draw(&Text::new(name.to_string(), (x + 20, 8), key_font.clone()))?;
            let w = key_font.box_size(name).map_or(0, |(w, _)| w) as i32;
            x += 20 + w + 28;
        }
        let cells = grid.split_evenly((layout.rows, layout.cols));
        for (panel, area) in panels.iter().zip(&cells) {
            let bars = &panel.bars;
            let mut chart = ChartBuilder::on(area)
                .caption(&panel.title, ("sans-serif", 17))
                .margin(BAR_CHART_MARGIN)
                .x_label_area_size(28)
                .y_label_area_size(BAR_CHART_Y_LABELS)
                .build_cartesian_2d(-0.5f64..bars.len() as f64 - 0.5, 0.0..top)?;
            chart
                .configure_mesh()
                .y_desc(y_label)
                .y_labels(6)
                .y_label_formatter(&|y| tick_label(*y, top))
                .x_labels(bars.len())
                .x_label_formatter(&|x| {
                    let i = x.round() as i64;
                    if (x - i as f64).abs() < 1e-6 && i >= 0 {
                        bars.get(i as usize)
                            .map(|b| b.label.clone())
                            .unwrap_or_default()
                    } else {
                        String::new()
                    }
                })
                .disable_x_mesh()
                .label_style(("sans-serif", BAR_LABEL_PX))
                .draw()?;
            for k in 0..segment_names.len() {
                let color = PALETTE[k % PALETTE.len()];
                chart.draw_series(bars.iter().enumerate().map(|(i, bar)| {
                    let base: f64 = bar.segments[..k.min(bar.segments.len())].iter().sum();
                    let h = bar.segments.get(k).copied().unwrap_or(0.0);
                    Rectangle::new(
                        [(i as f64 - 0.35, base), (i as f64 + 0.35, base + h)],
                        color.filled(),
                    )
                }))?;
            }
        }
        Ok(())
    })
}

/// A line with a shaded band (mean ± spread) per series over a shared x axis.
pub struct BandSeries {
    pub label: String,
    /// Palette slot ([`colour_slots`]).
    pub colour: usize,
    /// A dashed mean line (e.g. ankles beside solid hips of one leg's colour).
    pub dashed: bool,
    pub x: Vec<f64>,
    pub mean: Vec<f64>,
    pub low: Vec<f64>,
    pub high: Vec<f64>,
}

pub fn bands(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[BandSeries],
    vertical_marker: Option<f64>,
    legend_at: SeriesLabelPosition,
) -> Result<(), PlotError> {
    let finite = |v: &f64| v.is_finite();
    let xs = series
        .iter()
        .flat_map(|s| s.x.iter().copied())
        .filter(finite);
    let (x0, x1) = min_max(xs).unwrap_or((0.0, 1.0));
    let ys = series
        .iter()
        .flat_map(|s| s.low.iter().chain(&s.high).copied())
        .filter(finite);
    let (y0, y1) = padded(min_max(ys).unwrap_or((0.0, 1.0)));
    render(path, (900, 520), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 24))
            .margin(16)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1.max(x0 + 1e-9), y0..y1)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .x_label_formatter(&|x| tick_label(*x, x1 - x0))
            .y_label_formatter(&|y| tick_label(*y, y1 - y0))
            .label_style(("sans-serif", 15))
            .draw()?;
        for ser in series {
            let color = palette(ser.colour);
            let upper: Vec<(f64, f64)> = ser
                .x
                .iter()
                .copied()
                .zip(ser.high.iter().copied())
                .collect();
            let lower: Vec<(f64, f64)> = ser
                .x
                .iter()
                .copied()
                .zip(ser.low.iter().copied())
                .rev()
                .collect();
            chart.draw_series(std::iter::once(Polygon::new(
                [upper, lower].concat(),
                color.mix(0.18),
            )))?;
            let mean = || ser.x.iter().copied().zip(ser.mean.iter().copied());
            let style = color.stroke_width(2);
            let drawn = if ser.dashed {
                chart.draw_series(DashedLineSeries::new(mean(), 8, 5, style))?
            } else {
                chart.draw_series(LineSeries::new(mean(), style))?
            };
            let dashed = ser.dashed;
            drawn.label(ser.label.clone()).legend(move |(x, y)| {
                if dashed {
                    PathElement::new(vec![(x, y), (x + 8, y)], style)
                } else {
                    PathElement::new(vec![(x, y), (x + 20, y)], style)
                }
            });
        }
        if let Some(x) = vertical_marker {
            chart.draw_series(LineSeries::new([(x, y0), (x, y1)], BLACK.mix(0.6)))?;
        }
        chart
            .configure_series_labels()
            .position(legend_at)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()?;
        Ok(())
    })
}

/// A 2-D scatter, one colour per class, with a legend.
pub fn scatter(
    path: &Path,
    title: &str,
    axes: (&str, &str),
    classes: &[(String, Vec<(f64, f64)>)],
) -> Result<(), PlotError> {
    let all = || classes.iter().flat_map(|(_, p)| p.iter());
    let (x0, x1) = padded(min_max(all().map(|p| p.0)).unwrap_or((0.0, 1.0)));
    let (y0, y1) = padded(min_max(all().map(|p| p.1)).unwrap_or((0.0, 1.0)));
    render(path, (820, 720), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 24))
            .margin(16)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)?;
        chart
            .configure_mesh()
            .x_desc(axes.0)
            .y_desc(axes.1)
            .x_label_formatter(&|x| tick_label(*x, x1 - x0))
            .y_label_formatter(&|y| tick_label(*y, y1 - y0))
            .label_style(("sans-serif", 15))
            .draw()?;
        let colors = viridis(classes.len());
        for ((label, points), color) in classes.iter().zip(colors) {
            chart
                .draw_series(
                    points
                        .iter()
                        .map(|&(x, y)| Circle::new((x, y), 3, color.mix(0.6).filled())),
                )?
                .label(label.clone())
                .legend(move |(x, y)| Circle::new((x + 10, y), 5, color.filled()));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()?;
        Ok(())
    })
}

/// `n` colours from plotters' viridis map, dark to light.
pub fn viridis(n: usize) -> Vec<RGBColor> {
    use plotters::style::colors::colormaps::{ColorMap, ViridisRGB};
    (0..n)
        .map(|i| {
            ViridisRGB.get_color(if n > 1 {
                i as f64 / (n - 1) as f64
            } else {
                0.0
            })
        })
        .collect()
}

fn min_max(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    values.fold(None, |acc, v| match acc {
        None => Some((v, v)),
        Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
    })
}

fn padded((lo, hi): (f64, f64)) -> (f64, f64) {
    let pad = ((hi - lo) * 0.05).max(1e-6);
    (lo - pad, hi + pad)
}

/// One line of a [`LinePanel`]. Lines share a colour (and one legend entry) by `name`.
pub struct Line {
    pub name: String,
    /// Palette slot ([`colour_slots`]).
    pub colour: usize,
    /// A point whose y is not finite (e.g. NaN) breaks the line: nothing is drawn across it.
    pub points: Vec<(f64, f64)>,
    /// Thin and pale (one seed of a group), under the group's bold line.
    pub faint: bool,
}

/// One panel of a multi-panel line figure: a title, a y label and lines.
pub struct LinePanel {
    pub title: String,
    pub y_label: String,
    pub lines: Vec<Line>,
    /// A fixed y range (e.g. 0…1 for a rate); otherwise fitted to the data.
    pub y_range: Option<(f64, f64)>,
    /// Where this panel's legend goes; `None`: no legend (another panel has it).
    pub legend: Option<SeriesLabelPosition>,
}

/// Panels on a grid of `columns`, sharing the x label; one legend entry per line name.
pub fn line_panels(
    path: &Path,
    x_label: &str,
    columns: usize,
    panels: &[LinePanel],
) -> Result<(), PlotError> {
    let columns = columns.max(1);
    let rows = panels.len().div_ceil(columns).max(1);
    render(path, (560 * columns as u32, 380 * rows as u32), |root| {
        for (area, panel) in root.split_evenly((rows, columns)).iter().zip(panels) {
            let points = || panel.lines.iter().flat_map(|l| l.points.iter().copied());
            let (x0, x1) =
                min_max(points().map(|p| p.0).filter(|v| v.is_finite())).unwrap_or((0.0, 1.0));
            let (y0, y1) = panel.y_range.unwrap_or_else(|| {
                padded(
                    min_max(points().map(|p| p.1).filter(|v| v.is_finite())).unwrap_or((0.0, 1.0)),
                )
            });
            let mut chart = ChartBuilder::on(area)
                .caption(&panel.title, ("sans-serif", 20))
                .margin(12)
                .x_label_area_size(36)
                .y_label_area_size(60)
                .build_cartesian_2d(x0..x1.max(x0 + 1e-9), y0..y1)?;
            chart
                .configure_mesh()
                .x_desc(x_label)
                .y_desc(&panel.y_label)
                .x_label_formatter(&|x| thousands(*x))
                .y_label_formatter(&|y| tick_label(*y, y1 - y0))
                .label_style(("sans-serif", 13))
                .draw()?;
            // Faint lines first, so every bold line is drawn over them.
            let order = panel
                .lines
                .iter()
                .filter(|l| l.faint)
                .chain(panel.lines.iter().filter(|l| !l.faint));
            let mut labelled: Vec<&str> = Vec::new();
            for line in order {
                let color = palette(line.colour);
                let style = if line.faint {
                    color.mix(0.3).stroke_width(1)
                } else {
                    color.stroke_width(2)
                };
                // One legend entry per name, from its bold line if it has one.
                let label = !labelled.contains(&line.name.as_str())
                    && (!line.faint || panel.lines.iter().all(|l| l.name != line.name || l.faint));
                let mut pieces = segments(&line.points);
                if pieces.is_empty() {
                    pieces.push(Vec::new()); // still one (empty) series for the legend
                }
                for (i, piece) in pieces.into_iter().enumerate() {
                    let series = chart.draw_series(stroke_segments(&piece, style))?;
                    if label && i == 0 {
                        series.label(line.name.clone()).legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(3))
                        });
                        labelled.push(&line.name);
                    }
                }
            }
            if let Some(position) = panel.legend.clone() {
                chart
                    .configure_series_labels()
                    .position(position)
                    .background_style(WHITE.mix(0.85))
                    .border_style(BLACK)
                    .label_font(("sans-serif", 13))
                    .draw()?;
            }
        }
        Ok(())
    })
}

/// A polyline as one path per segment. plotters fills a line wider than a pixel as a single
/// polygon, and where a dense, jagged line (a rolling mean over hundreds of episodes) folds back
/// on itself the fill leaves holes, so the line looked hollow and broken; each segment alone is
/// a simple quadrilateral.
fn stroke_segments(
    points: &[(f64, f64)],
    style: ShapeStyle,
) -> impl Iterator<Item = PathElement<(f64, f64)>> + '_ {
    let single = (points.len() == 1).then(|| PathElement::new(vec![points[0]], style));
    points
        .windows(2)
        .map(move |w| PathElement::new(vec![w[0], w[1]], style))
        .chain(single)
}

/// The runs of finite points of `line`, split wherever y is not finite.
fn segments(line: &[(f64, f64)]) -> Vec<Vec<(f64, f64)>> {
    line.split(|p| !p.1.is_finite())
        .filter(|piece| !piece.is_empty())
        .map(<[_]>::to_vec)
        .collect()
}

/// Axis labels for step counts: 120000 → "120k".
fn thousands(x: f64) -> String {
    if x.abs() >= 1000.0 {
        format!("{}k", (x / 1000.0).round())
    } else {
        format!("{}", x.round())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bar_panels_fit_their_labels() {
        register_font();
        let font = ("sans-serif", BAR_LABEL_PX).into_font();
        // DejaVu Sans at 13 px: about 0.55 em a character, so "ood-intermittent" (16) is ~114 px.
        let (w, _) = font
            .box_size("ood-intermittent")
            .expect("the bundled font measures");
        assert!((85..=145).contains(&w), "{w} px");
        let panels = |labels: &[&str]| -> Vec<BarPanel> {
            [
                "baseline",
                "encoder-lstm-aux",
                "encoder-lstm",
                "encoder-mlp",
            ]
            .iter()
            .map(|m| BarPanel {
                title: m.to_string(),
                bars: labels
                    .iter()
                    .map(|l| StackedBar {
                        label: l.to_string(),
                        segments: vec![100.0],
                    })
                    .collect(),
            })
            .collect()
        };
        // Four models × three conditions: one row of four panels at the default width.
        let eval = bar_layout(&panels(&["healthy", "mild", "severe"]));
        assert_eq!((eval.cols, eval.rows, eval.width), (4, 1, 1200));
        // Four models × the `ood` suite's eight columns: a panel per row, each bar's slot at
        // least its widest label and the gap.
        let ood = [
            "healthy",
            "ood-ankle",
            "ood-leg",
            "ood-diagonal",
            "ood-decay",
            "ood-intermittent",
            "ood-sides",
            "ood-late-fault",
        ];
        let layout = bar_layout(&panels(&ood));
        assert_eq!((layout.cols, layout.rows), (1, 4));
        let slot = (layout.width - 2 * BAR_CHART_MARGIN - BAR_CHART_Y_LABELS) / ood.len() as u32;
        assert!(
            slot >= w + BAR_LABEL_GAP,
            "slot {slot} px for a {w}-px label"
        );
    }

    #[test]
    fn y_ticks_stop_at_the_data() {
        // A success axis: 0…100 %, ticks every 20, light lines every 4, none in the legend's
        // headroom above 100.
        let (bold, light, decimals) = y_key_points((0.0, 100.0));
        assert_eq!(bold, [0.0, 20.0, 40.0, 60.0, 80.0, 100.0]);
        assert_eq!(decimals, 0);
        assert_eq!(light.len(), 5 * 4);
        assert!(
            light
                .iter()
                .all(|v| (0.0..100.0).contains(v) && v % 4.0 == 0.0)
        );
        assert!(
            !light.iter().any(|v| v % 20.0 == 0.0),
            "no light line on a bold one"
        );
        // Distance axes of a few metres: whole metres up to 5 (not past 5.2), or half metres.
        assert_eq!(y_key_points((0.0, 5.2)).0, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        let (bold, _, decimals) = y_key_points((0.0, 2.6));
        assert_eq!(bold, [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]);
        assert_eq!(decimals, 1);
        // A range off zero, a fine one, and one with no width (a single value).
        assert_eq!(y_key_points((-3.0, 7.0)).0, [-2.0, 0.0, 2.0, 4.0, 6.0]);
        assert_eq!(y_key_points((0.0, 0.1)).2, 2);
        assert_eq!(y_key_points((4.0, 4.0)), (vec![4.0], vec![], 0));
    }

    #[test]
    fn tick_labels_carry_the_decimals_the_span_needs() {
        assert_eq!(tick_label(700.0, 1000.0), "700");
        assert_eq!(tick_label(-300.0, 1000.0), "-300");
        assert_eq!(tick_label(12.0, 20.0), "12");
        assert_eq!(tick_label(7.5, 6.0), "7.5"); // α or joints: a tenth of 6 is 0.6
        assert_eq!(tick_label(0.25, 0.1), "0.25"); // the aux loss: 0.19…0.29
        assert_eq!(tick_label(0.8, 0.8), "0.80");
        assert_eq!(tick_label(-1e-17, 0.8), "0.00");
        assert_eq!(tick_label(3.0, 0.0), "3");
    }

    #[test]
    fn a_non_finite_y_breaks_a_line() {
        let line = [
            (0.0, 1.0),
            (1.0, 2.0),
            (2.0, f64::NAN),
            (3.0, 3.0),
            (4.0, f64::INFINITY),
            (5.0, f64::NAN),
        ];
        assert_eq!(
            segments(&line),
            vec![vec![(0.0, 1.0), (1.0, 2.0)], vec![(3.0, 3.0)]]
        );
        assert!(segments(&[(0.0, f64::NAN)]).is_empty());
    }

    #[test]
    fn a_dense_jagged_bold_line_is_painted_solid() {
        // 3000 points zigzagging between 0.2 and 0.8 across ~470 px: every pixel column between
        // them is crossed many times, so the band they span must be painted in the line's
        // colour throughout (plotters' one-polygon wide line left it hollow in patches).
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("zigzag.png");
        let points = (0..3000)
            .map(|i| (i as f64, if i % 2 == 0 { 0.2 } else { 0.8 }))
            .collect();
        let panel = LinePanel {
            title: "zigzag".into(),
            y_label: "y".into(),
            lines: vec![Line {
                name: "line".into(),
                colour: 1,
                points,
                faint: false,
            }],
            y_range: Some((0.0, 1.0)),
            legend: None,
        };
        line_panels(&path, "x", 1, &[panel]).unwrap();
        let decoder =
            png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        let channels = info.color_type.samples();
        let colour = palette(1);
        let painted = |x: u32, y: u32| {
            let i = (y * info.width + x) as usize * channels;
            buf[i..i + 3] == [colour.0, colour.1, colour.2]
        };
        // The band: the line colour's bounding box, shrunk by the 2 px stroke at each edge.
        let hits: Vec<(u32, u32)> = (0..info.height)
            .flat_map(|y| (0..info.width).map(move |x| (x, y)))
            .filter(|&(x, y)| painted(x, y))
            .collect();
        let (x0, x1) = (
            hits.iter().map(|p| p.0).min().unwrap() + 2,
            hits.iter().map(|p| p.0).max().unwrap() - 2,
        );
        let (y0, y1) = (
            hits.iter().map(|p| p.1).min().unwrap() + 2,
            hits.iter().map(|p| p.1).max().unwrap() - 2,
        );
        assert!(
            x1 > x0 + 300 && y1 > y0 + 100,
            "band {x0}..{x1} × {y0}..{y1}"
        );
        let band = (x0..=x1).flat_map(|x| (y0..=y1).map(move |y| (x, y)));
        let holes = band.clone().filter(|&(x, y)| !painted(x, y)).count();
        assert_eq!(
            holes,
            0,
            "{holes} of {} band pixels unpainted",
            band.count()
        );
    }

    #[test]
    fn listed_keys_keep_their_colour_and_others_take_free_slots() {
        let fixed = ["baseline", "lstm", "mlp"];
        // Without the baseline, lstm and mlp keep slots 1 and 2.
        assert_eq!(colour_slots(&["lstm", "mlp"], &fixed), [1, 2]);
        assert_eq!(
            colour_slots(&["mlp", "baseline", "lstm", "mlp"], &fixed),
            [2, 0, 1, 2]
        );
        // Other keys fill the slots this figure leaves free, one per key.
        assert_eq!(
            colour_slots(&["a", "lstm", "b", "a", "c"], &fixed),
            [0, 1, 2, 0, 3]
        );
        assert_eq!(colour_slots(&["x", "y"], &[]), [0, 1]);
    }
}
