//! PNG plots of evaluation results: TRE per measurement category and method (box plots with a
//! mean marker), and the distribution of per-scenario TRE per method (empirical cumulative
//! distribution). Pure: each function returns the PNG file's bytes and the caller writes them.
//! Text is drawn with DejaVu Sans embedded in the binary (`assets/fonts`, Bitstream Vera / Arev
//! license), never with a system font, so plots render the same on a machine without fonts.

use super::report::{CATEGORY_ORDER, ScenarioResult};
use crate::eval::EvalError;
use crate::util::quantile;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;
use std::sync::OnceLock;

/// DejaVu Sans 2.37 (see `assets/fonts/LICENSE-DejaVu.txt`).
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
/// The family name the embedded font is registered under.
const FAMILY: &str = "sans-serif";

/// Width and height of every plot (pixels).
pub const PLOT_SIZE: (u32, u32) = (1200, 720);

/// Colours of the methods, in order of first appearance (then cycling).
const COLOURS: [RGBColor; 5] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
];

fn font() -> Result<(), EvalError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED
        .get_or_init(|| plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if ok {
        Ok(())
    } else {
        Err(EvalError::Plot(
            "the embedded font DejaVuSans.ttf could not be parsed".into(),
        ))
    }
}

/// Box-plot statistics of a sample (linear-interpolated quantiles; mm for TRE).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxStats {
    /// Sample size.
    pub n: usize,
    /// Mean.
    pub mean: f64,
    /// 5th percentile (lower whisker).
    pub p5: f64,
    /// First quartile.
    pub q1: f64,
    /// Median.
    pub median: f64,
    /// Third quartile.
    pub q3: f64,
    /// 95th percentile (upper whisker).
    pub p95: f64,
    /// Largest value.
    pub max: f64,
}

impl BoxStats {
    /// Statistics of the finite values of `values`; None when there is none.
    pub fn of(values: &[f64]) -> Option<Self> {
        let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(Self {
            n: v.len(),
            mean: v.iter().sum::<f64>() / v.len() as f64,
            p5: quantile(&v, 0.05),
            q1: quantile(&v, 0.25),
            median: quantile(&v, 0.5),
            q3: quantile(&v, 0.75),
            p95: quantile(&v, 0.95),
            max: v[v.len() - 1],
        })
    }
}

/// Methods in order of first appearance, with their registered TREs (mm).
fn by_method(results: &[ScenarioResult]) -> Vec<(String, Vec<&ScenarioResult>)> {
    let mut out: Vec<(String, Vec<&ScenarioResult>)> = Vec::new();
    for r in results {
        match out.iter_mut().find(|(m, _)| *m == r.method) {
            Some((_, v)) => v.push(r),
            None => out.push((r.method.clone(), vec![r])),
        }
    }
    out
}

fn tre_of(rs: &[&ScenarioResult]) -> Vec<f64> {
    rs.iter().filter_map(|r| r.tre.map(|t| t.tre_mm)).collect()
}

/// Scenarios of the split (distinct scenario ids over all methods).
fn scenario_count(results: &[ScenarioResult]) -> usize {
    results
        .iter()
        .map(|r| r.scenario.as_str())
        .collect::<std::collections::BTreeSet<_>>()
        .len()
}

/// Renders into an RGB buffer with `draw`, then encodes it as PNG.
fn render(
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), EvalError>,
) -> Result<Vec<u8>, EvalError> {
    font()?;
    let (w, h) = PLOT_SIZE;
    let mut rgb = vec![0u8; 3 * w as usize * h as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE)?;
        draw(&root)?;
        root.present()?;
    }
    let mut png_bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut png_bytes, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc
            .write_header()
            .map_err(|e| EvalError::Plot(format!("PNG header: {e}")))?;
        writer
            .write_image_data(&rgb)
            .map_err(|e| EvalError::Plot(format!("PNG data: {e}")))?;
    }
    Ok(png_bytes)
}

fn text(size: u32) -> TextStyle<'static> {
    (FAMILY, size).into_font().color(&BLACK)
}

/// Grouped box plots of per-scenario TRE per measurement category ([`CATEGORY_ORDER`], then any
/// other category in name order) for each method: box = quartiles, line = median, whiskers = 5th
/// and 95th percentiles, diamond = mean. Failed registrations are left out (and counted in the
/// legend). Returns the PNG bytes ([`PLOT_SIZE`]).
pub fn tre_by_category_png(split: &str, results: &[ScenarioResult]) -> Result<Vec<u8>, EvalError> {
    let mut categories: Vec<String> = CATEGORY_ORDER.iter().map(|c| c.to_string()).collect();
    let mut extra: Vec<String> = results
        .iter()
        .map(|r| r.category.clone())
        .filter(|c| !categories.contains(c))
        .collect();
    extra.sort();
    extra.dedup();
    categories.extend(extra);
    // Only the categories that occur.
    categories.retain(|c| results.iter().any(|r| &r.category == c));
    let methods = by_method(results);
    let stats: Vec<Vec<Option<BoxStats>>> = methods
        .iter()
        .map(|(_, rs)| {
            categories
                .iter()
                .map(|c| {
                    let in_cat: Vec<&ScenarioResult> =
                        rs.iter().copied().filter(|r| &r.category == c).collect();
                    BoxStats::of(&tre_of(&in_cat))
                })
                .collect()
        })
        .collect();
    let top = stats
        .iter()
        .flatten()
        .flatten()
        .map(|s| s.p95.max(s.mean))
        .fold(0.0f64, f64::max);
    let ymax = if top > 0.0 { 1.3 * top } else { 1.0 };
    let ncat = categories.len().max(1);
    let nm = methods.len().max(1);
    let title = format!(
        "TRE by measurement category — split {split} ({} scenarios)",
        scenario_count(results)
    );
    render(|root| {
        let mut chart = ChartBuilder::on(root)
            .caption(&title, text(30))
            .margin(24)
            .x_label_area_size(70)
            .y_label_area_size(80)
            .build_cartesian_2d(-0.5f64..(ncat as f64 - 0.5), 0f64..ymax)?;
        let cats = categories.clone();
        let label = move |x: &f64| {
            let k = x.round();
            if (x - k).abs() < 1e-6 && k >= 0.0 && (k as usize) < cats.len() {
                cats[k as usize].clone()
            } else {
                String::new()
            }
        };
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(ncat)
            .x_label_formatter(&label)
            .y_labels(10)
            .x_desc("measurement category (anterior surface points + ultrasound planes)")
            .y_desc("TRE per scenario (mm, mean over mesh nodes)")
            .axis_desc_style(text(20))
            .label_style(text(17))
            .max_light_lines(4)
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        let slot = 0.8 / nm as f64;
        let half = 0.35 * slot;
        for (mi, (method, rs)) in methods.iter().enumerate() {
            let colour = COLOURS[mi % COLOURS.len()];
            let area = chart.plotting_area();
            let err = |e: DrawingAreaErrorKind<_>| EvalError::Plot(e.to_string());
            for (ci, s) in stats[mi].iter().enumerate() {
                let Some(s) = s else { continue };
                let x = ci as f64 - 0.4 + (mi as f64 + 0.5) * slot;
                let (x0, x1) = (x - half, x + half);
                let line = colour.stroke_width(2);
                let cap = 0.5 * half;
                area.draw(&Rectangle::new(
                    [(x0, s.q1), (x1, s.q3)],
                    colour.mix(0.3).filled(),
                ))
                .map_err(err)?;
                area.draw(&Rectangle::new([(x0, s.q1), (x1, s.q3)], line))
                    .map_err(err)?;
                for seg in [
                    [(x, s.q3), (x, s.p95)],
                    [(x, s.q1), (x, s.p5)],
                    [(x - cap, s.p95), (x + cap, s.p95)],
                    [(x - cap, s.p5), (x + cap, s.p5)],
                ] {
                    area.draw(&PathElement::new(seg.to_vec(), line))
                        .map_err(err)?;
                }
                area.draw(&PathElement::new(
                    vec![(x0, s.median), (x1, s.median)],
                    colour.stroke_width(4),
                ))
                .map_err(err)?;
                area.draw(
                    &(EmptyElement::at((x, s.mean))
                        + Polygon::new(vec![(0, -7), (7, 0), (0, 7), (-7, 0)], WHITE.filled())
                        + PathElement::new(
                            vec![(0, -7), (7, 0), (0, 7), (-7, 0), (0, -7)],
                            BLACK.stroke_width(2),
                        )),
                )
                .map_err(err)?;
            }
            let ok = rs.iter().filter(|r| r.tre.is_some()).count();
            let failed = rs.len() - ok;
            let name = if failed > 0 {
                format!("{method} (n = {ok}, {failed} failed)")
            } else {
                format!("{method} (n = {ok})")
            };
            chart
                .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())?
                .label(name)
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 8), (x + 20, y + 8)], colour.mix(0.5).filled())
                });
        }
        // A legend entry for the marker conventions.
        chart
            .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())?
            .label("◇ mean; box: quartiles, line: median, whiskers: 5th–95th pct")
            .legend(|(x, y)| {
                EmptyElement::at((x + 10, y))
                    + Polygon::new(vec![(0, -6), (6, 0), (0, 6), (-6, 0)], WHITE.filled())
                    + PathElement::new(
                        vec![(0, -6), (6, 0), (0, 6), (-6, 0), (0, -6)],
                        BLACK.stroke_width(2),
                    )
            });
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.9))
            .border_style(BLACK)
            .label_font(text(17))
            .draw()?;
        Ok(())
    })
}

/// Empirical cumulative distribution of per-scenario TRE for each method (fraction of a
/// method's registered scenarios with TRE ≤ x), with each method's median in the legend.
/// Returns the PNG bytes ([`PLOT_SIZE`]).
pub fn tre_cdf_png(split: &str, results: &[ScenarioResult]) -> Result<Vec<u8>, EvalError> {
    let methods = by_method(results);
    let sorted: Vec<Vec<f64>> = methods
        .iter()
        .map(|(_, rs)| {
            let mut v = tre_of(rs);
            v.retain(|x| x.is_finite());
            v.sort_by(f64::total_cmp);
            v
        })
        .collect();
    let top = sorted
        .iter()
        .filter_map(|v| v.last().copied())
        .fold(0.0f64, f64::max);
    let xmax = if top > 0.0 { 1.05 * top } else { 1.0 };
    let title = format!(
        "Per-scenario TRE distribution — split {split} ({} scenarios)",
        scenario_count(results)
    );
    render(|root| {
        let mut chart = ChartBuilder::on(root)
            .caption(&title, text(30))
            .margin(24)
            .x_label_area_size(70)
            .y_label_area_size(80)
            .build_cartesian_2d(0f64..xmax, 0f64..1.03)?;
        chart
            .configure_mesh()
            .x_labels(12)
            .y_labels(11)
            .x_desc("TRE per scenario (mm, mean over mesh nodes)")
            .y_desc("fraction of scenarios with TRE ≤ x")
            .axis_desc_style(text(20))
            .label_style(text(17))
            .max_light_lines(4)
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        for (mi, ((method, rs), v)) in methods.iter().zip(&sorted).enumerate() {
            let colour = COLOURS[mi % COLOURS.len()];
            let n = v.len();
            let mut path = Vec::with_capacity(2 * n + 2);
            path.push((0.0, 0.0));
            for (i, &x) in v.iter().enumerate() {
                path.push((x, i as f64 / n as f64));
                path.push((x, (i + 1) as f64 / n as f64));
            }
            if let Some(&last) = v.last() {
                path.push((xmax.max(last), 1.0));
            }
            let failed = rs.len() - n;
            let name = match BoxStats::of(v) {
                Some(s) if failed > 0 => format!(
                    "{method}: median {:.2} mm, mean {:.2} mm (n = {n}, {failed} failed)",
                    s.median, s.mean
                ),
                Some(s) => format!(
                    "{method}: median {:.2} mm, mean {:.2} mm (n = {n})",
                    s.median, s.mean
                ),
                None => format!("{method}: no registration succeeded ({failed} failed)"),
            };
            let elements = (n > 0)
                .then(|| PathElement::new(path, colour.stroke_width(3)))
                .into_iter();
            chart
                .draw_series(elements)?
                .label(name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 24, y)], colour.stroke_width(3))
                });
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.9))
            .border_style(BLACK)
            .label_font(text(17))
            .draw()?;
        Ok(())
    })
}

/// A line chart of named series `(x, y)` (e.g. training and validation loss per epoch), each
/// series in its own colour with its name in the legend. Returns the PNG bytes.
pub fn line_chart_png(
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<Vec<u8>, EvalError> {
    let pts = series
        .iter()
        .flat_map(|s| s.1.iter())
        .filter(|p| p.0.is_finite() && p.1.is_finite());
    let (mut x0, mut x1, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, 0f64);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y1 = y1.max(y);
    }
    if !x0.is_finite() {
        (x0, x1) = (0.0, 1.0);
    }
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    let y1 = if y1 > 0.0 { 1.05 * y1 } else { 1.0 };
    render(|root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, text(30))
            .margin(24)
            .x_label_area_size(70)
            .y_label_area_size(90)
            .build_cartesian_2d(x0..x1, 0f64..y1)?;
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .y_desc(y_desc)
            .axis_desc_style(text(20))
            .label_style(text(17))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        for (i, (name, pts)) in series.iter().enumerate() {
            let colour = COLOURS[i % COLOURS.len()];
            let pts: Vec<(f64, f64)> = pts
                .iter()
                .copied()
                .filter(|p| p.0.is_finite() && p.1.is_finite())
                .collect();
            chart
                .draw_series(std::iter::once(PathElement::new(
                    pts,
                    colour.stroke_width(3),
                )))?
                .label(name.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 24, y)], colour.stroke_width(3))
                });
        }
        chart
            .configure_series_labels()
            .label_font(text(18))
            .background_style(WHITE.mix(0.9))
            .border_style(BLACK)
            .draw()?;
        Ok(())
    })
}

/// Grouped bars: one group per label on the x axis, one bar per series in each group (its own
/// colour, named in the legend); NaN values are left out. Values may be negative (the axis then
/// spans them). Returns the PNG bytes ([`PLOT_SIZE`]).
pub fn grouped_bars_png(
    title: &str,
    x_desc: &str,
    y_desc: &str,
    groups: &[String],
    series: &[(String, Vec<f64>)],
) -> Result<Vec<u8>, EvalError> {
    let vals = series
        .iter()
        .flat_map(|s| s.1.iter())
        .copied()
        .filter(|v| v.is_finite());
    let (mut lo, mut hi) = (0f64, 0f64);
    for v in vals {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if hi <= lo {
        hi = lo + 1.0;
    }
    let pad = 0.1 * (hi - lo);
    let (y0, y1) = (if lo < 0.0 { lo - pad } else { 0.0 }, hi + pad);
    let ng = groups.len().max(1);
    let ns = series.len().max(1);
    render(|root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, text(28))
            .margin(24)
            .x_label_area_size(90)
            .y_label_area_size(90)
            .build_cartesian_2d(-0.5f64..(ng as f64 - 0.5), y0..y1)?;
        let names = groups.to_vec();
        let label = move |x: &f64| {
            let k = x.round();
            if (x - k).abs() < 1e-6 && k >= 0.0 && (k as usize) < names.len() {
                names[k as usize].clone()
            } else {
                String::new()
            }
        };
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(ng)
            .x_label_formatter(&label)
            .x_desc(x_desc)
            .y_desc(y_desc)
            .axis_desc_style(text(20))
            .label_style(text(15))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        let slot = 0.8 / ns as f64;
        for (si, (name, v)) in series.iter().enumerate() {
            let colour = COLOURS[si % COLOURS.len()];
            let bars: Vec<Rectangle<(f64, f64)>> = v
                .iter()
                .enumerate()
                .filter(|(_, y)| y.is_finite())
                .map(|(g, &y)| {
                    let x0 = g as f64 - 0.4 + si as f64 * slot;
                    Rectangle::new([(x0, 0.0), (x0 + 0.9 * slot, y)], colour.filled())
                })
                .collect();
            chart
                .draw_series(bars)?
                .label(name.clone())
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 8), (x + 20, y + 8)], colour.filled())
                });
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .label_font(text(17))
            .background_style(WHITE.mix(0.9))
            .border_style(BLACK)
            .draw()?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bars are drawn: the image has the plot's size, and pixels of each series' colour
    /// appear (a positive and a negative bar).
    #[test]
    fn grouped_bars_draw_each_series() {
        let png = grouped_bars_png(
            "t",
            "x",
            "y",
            &["a".into(), "b".into()],
            &[
                ("before".into(), vec![2.0, 1.0]),
                ("after".into(), vec![-1.0, f64::NAN]),
            ],
        )
        .unwrap();
        let dec = ::png::Decoder::new(std::io::Cursor::new(png));
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), PLOT_SIZE);
        let ch = info.color_type.samples();
        let has = |c: RGBColor| {
            buf.chunks_exact(ch)
                .any(|p| p[0] == c.0 && p[1] == c.1 && p[2] == c.2)
        };
        assert!(has(COLOURS[0]) && has(COLOURS[1]));
    }
}
