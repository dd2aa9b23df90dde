//! Line charts as SVG, drawn with the `plotters` crate, for the quality report and the frequency
//! response.
//!
//! Only plotters' SVG backend is used: it writes `<text>` elements and leaves glyphs to the
//! viewer, so no font files or system libraries (fontconfig, FreeType) are needed to build or
//! run. The SVG can be saved as a file or inlined into HTML as it is.
//!
//! A [`LineChart`] is plain data (title, axis labels, [`Series`]); [`LineChart::to_svg`] draws it.
//! Non-finite points (and non-positive ones on a logarithmic axis) are left out, so a curve with
//! gaps still draws.

use std::ops::Range;

use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::prelude::*;

use super::EvalError;

/// A colour per method, shared by the plots of a report so that a method looks the same
/// everywhere.
pub mod colours {
    /// The noisy input: grey.
    pub const NOISY: [u8; 3] = [128, 128, 128];
    /// The paper's operator: red.
    pub const FAITHFUL: [u8; 3] = [204, 51, 51];
    /// The bilateral baseline: blue.
    pub const BILATERAL: [u8; 3] = [40, 90, 200];
    /// qemd's default operator: green.
    pub const DEFAULT: [u8; 3] = [20, 150, 70];
    /// A reference curve (the clean surface): black.
    pub const REFERENCE: [u8; 3] = [0, 0, 0];
    /// Anything else: purple.
    pub const OTHER: [u8; 3] = [140, 60, 170];
}

/// Where the legend goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Corner {
    /// Top left.
    #[default]
    UpperLeft,
    /// Top right.
    UpperRight,
    /// Bottom left.
    LowerLeft,
    /// Bottom right.
    LowerRight,
}

/// One line of a chart.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend entry.
    pub name: String,
    /// (x, y) points, drawn in order.
    pub points: Vec<(f64, f64)>,
    /// RGB colour.
    pub colour: [u8; 3],
    /// Dashed instead of solid.
    pub dashed: bool,
    /// Draw a dot at every point.
    pub markers: bool,
}

impl Series {
    /// A solid line without markers.
    pub fn new(name: impl Into<String>, points: Vec<(f64, f64)>, colour: [u8; 3]) -> Series {
        Series {
            name: name.into(),
            points,
            colour,
            dashed: false,
            markers: false,
        }
    }
}

/// A chart of lines over a shared pair of axes.
#[derive(Debug, Clone, PartialEq)]
pub struct LineChart {
    /// Caption above the chart.
    pub title: String,
    /// Label of the x axis.
    pub x_label: String,
    /// Label of the y axis.
    pub y_label: String,
    /// The lines, drawn in order (later ones on top).
    pub series: Vec<Series>,
    /// Logarithmic y axis.
    pub log_y: bool,
    /// Fixed x range; `None` fits the data.
    pub x_range: Option<(f64, f64)>,
    /// Fixed y range; `None` fits the data (from 0 on a linear axis when all values are ≥ 0).
    pub y_range: Option<(f64, f64)>,
    /// Horizontal reference lines (e.g. a gain of 1), drawn thin and grey.
    pub h_lines: Vec<f64>,
    /// Legend position.
    pub legend: Corner,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

impl LineChart {
    /// An empty 720 × 440 chart with linear axes.
    pub fn new(
        title: impl Into<String>,
        x_label: impl Into<String>,
        y_label: impl Into<String>,
    ) -> LineChart {
        LineChart {
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            series: Vec::new(),
            log_y: false,
            x_range: None,
            y_range: None,
            h_lines: Vec::new(),
            legend: Corner::UpperLeft,
            width: 720,
            height: 440,
        }
    }

    /// The points of a series that can be drawn on these axes.
    fn drawable(&self, s: &Series) -> Vec<(f64, f64)> {
        s.points
            .iter()
            .copied()
            .filter(|&(x, y)| x.is_finite() && y.is_finite() && (!self.log_y || y > 0.0))
            .collect()
    }

    /// The x and y ranges: fixed ones as given, otherwise the data's with a margin.
    fn ranges(&self) -> Result<(Range<f64>, Range<f64>), EvalError> {
        let pts: Vec<(f64, f64)> = self.series.iter().flat_map(|s| self.drawable(s)).collect();
        let bad = |detail: String| EvalError::Param {
            name: "chart",
            detail,
        };
        let fit = |v: &mut dyn Iterator<Item = f64>| -> Option<(f64, f64)> {
            v.fold(None, |acc, x| match acc {
                None => Some((x, x)),
                Some((lo, hi)) => Some((f64::min(lo, x), f64::max(hi, x))),
            })
        };
        let x = match self.x_range {
            Some(r) => r,
            None => fit(&mut pts.iter().map(|p| p.0))
                .ok_or_else(|| bad(format!("`{}` has no finite points", self.title)))?,
        };
        let y = match self.y_range {
            Some(r) => r,
            None => {
                let (lo, hi) = fit(&mut pts.iter().map(|p| p.1))
                    .ok_or_else(|| bad(format!("`{}` has no finite points", self.title)))?;
                if self.log_y {
                    (lo / 1.5, hi * 1.5)
                } else {
                    let lo = if lo >= 0.0 { 0.0 } else { lo };
                    let pad = (hi - lo).abs().max(hi.abs() * 0.1).max(1e-12) * 0.08;
                    (if lo == 0.0 { 0.0 } else { lo - pad }, hi + pad)
                }
            }
        };
        let widen = |(lo, hi): (f64, f64)| {
            if hi > lo {
                lo..hi
            } else {
                let d = lo.abs().max(1.0) * 0.05;
                (lo - d)..(hi + d)
            }
        };
        let (x, y) = (widen(x), widen(y));
        let ok = |r: &Range<f64>| r.start.is_finite() && r.end.is_finite();
        if !ok(&x) || !ok(&y) || (self.log_y && y.start <= 0.0) {
            return Err(bad(format!(
                "`{}`: cannot draw the range x {x:?}, y {y:?}",
                self.title
            )));
        }
        Ok((x, y))
    }

    /// Draws the chart as an SVG document.
    ///
    /// # Errors
    /// [`EvalError::Param`] when no series has a drawable point or a size is zero;
    /// [`EvalError::Plot`] if plotters fails.
    pub fn to_svg(&self) -> Result<String, EvalError> {
        if self.width < 100 || self.height < 100 || self.width > 8192 || self.height > 8192 {
            return Err(EvalError::Param {
                name: "chart",
                detail: format!(
                    "size must be within 100..=8192 pixels, got {}×{}",
                    self.width, self.height
                ),
            });
        }
        let (x, y) = self.ranges()?;
        let mut buf = String::new();
        {
            let root =
                SVGBackend::with_string(&mut buf, (self.width, self.height)).into_drawing_area();
            let result = if self.log_y {
                self.draw(&root, x, y.log_scale())
            } else {
                self.draw(&root, x, y)
            };
            result.map_err(|e| EvalError::Plot(e.to_string()))?;
        }
        Ok(buf)
    }

    fn draw<Y>(
        &self,
        root: &DrawingArea<SVGBackend<'_>, plotters::coord::Shift>,
        x: Range<f64>,
        y: Y,
    ) -> Result<(), DrawingAreaErrorKind<<SVGBackend<'_> as DrawingBackend>::ErrorType>>
    where
        Y: AsRangedCoord<Value = f64>,
        Y::CoordDescType: ValueFormatter<f64>,
    {
        root.fill(&WHITE)?;
        let (x0, x1) = (x.start, x.end);
        let mut chart = ChartBuilder::on(root)
            .caption(&self.title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(42)
            .y_label_area_size(58)
            .build_cartesian_2d(x, y)?;
        let fmt = |v: &f64| short_number(*v);
        chart
            .configure_mesh()
            .x_labels(10)
            .y_labels(if self.log_y { 6 } else { 10 })
            .max_light_lines(if self.log_y { 1 } else { 4 })
            .x_desc(self.x_label.as_str())
            .y_desc(self.y_label.as_str())
            .x_label_formatter(&fmt)
            .y_label_formatter(&fmt)
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        for &h in &self.h_lines {
            if h.is_finite() && (!self.log_y || h > 0.0) {
                chart.draw_series(LineSeries::new(
                    [(x0, h), (x1, h)],
                    RGBColor(150, 150, 150).stroke_width(1),
                ))?;
            }
        }
        for s in &self.series {
            let pts = self.drawable(s);
            let [r, g, b] = s.colour;
            let colour = RGBColor(r, g, b);
            let style = colour.stroke_width(2);
            let anno = if s.dashed {
                chart.draw_series(DashedLineSeries::new(pts.clone(), 6, 4, style))?
            } else {
                chart.draw_series(LineSeries::new(pts.clone(), style))?
            };
            anno.label(s.name.as_str()).legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 22, y)], colour.stroke_width(2))
            });
            if s.markers {
                chart.draw_series(
                    pts.iter()
                        .map(|&p| Circle::new(p, 3, colour.filled()))
                        .collect::<Vec<_>>(),
                )?;
            }
        }
        chart
            .configure_series_labels()
            .position(match self.legend {
                Corner::UpperLeft => SeriesLabelPosition::UpperLeft,
                Corner::UpperRight => SeriesLabelPosition::UpperRight,
                Corner::LowerLeft => SeriesLabelPosition::LowerLeft,
                Corner::LowerRight => SeriesLabelPosition::LowerRight,
            })
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(180, 180, 180))
            .draw()?;
        root.present()?;
        Ok(())
    }
}

/// A compact axis label: at most four significant digits, no trailing zeros.
fn short_number(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    let s = if !(1e-3..1e5).contains(&a) {
        format!("{v:.1e}")
    } else {
        let decimals = (3 - a.log10().floor() as i32).clamp(0, 6) as usize;
        format!("{v:.decimals$}")
    };
    if s.contains('.') && !s.contains('e') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_lines_legend_and_log_axes() {
        let mut c = LineChart::new("t <&>", "x", "y");
        c.series.push(Series::new(
            "alpha",
            vec![(0.0, 1.0), (1.0, 2.0), (2.0, f64::NAN), (3.0, 0.5)],
            colours::FAITHFUL,
        ));
        c.series.push(Series {
            dashed: true,
            markers: true,
            ..Series::new("beta", vec![(0.0, 0.1), (3.0, 0.2)], colours::DEFAULT)
        });
        c.h_lines.push(1.0);
        let svg = c.to_svg().unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert!(svg.contains("alpha") && svg.contains("beta"));
        assert!(svg.contains("&lt;&amp;&gt;"), "the title is escaped");
        c.log_y = true;
        let log = c.to_svg().unwrap();
        assert!(log.contains("<polyline") || log.contains("<path"));
        c.series.clear();
        assert!(matches!(c.to_svg(), Err(EvalError::Param { .. })));
    }

    #[test]
    fn short_numbers() {
        assert_eq!(short_number(0.0), "0");
        assert_eq!(short_number(20.0), "20");
        assert_eq!(short_number(0.25), "0.25");
        assert_eq!(short_number(12.345), "12.35");
        assert_eq!(short_number(2e-5), "2.0e-5");
    }
}
