//! The roster of the report and the frequency response: the three denoisers compared
//! ([`report_methods`]), their row names, chart colours and labels.

use super::plot::colours;
use super::table::{NOISY, TableMethod};
use crate::denoise::{Method, Params};

/// Name of the faithful row (the paper's operator).
pub const FAITHFUL: &str = "faithful";
/// Name of the bilateral row.
pub const BILATERAL: &str = "bilateral";
/// Name of qemd's default row.
pub const DEFAULT: &str = "default";

/// The three denoisers of the report, in row order: `faithful` (the paper's Algorithm 1 with
/// area-weighted normals: the paper's Table I QEM column), `bilateral` (Fleishman et al. 2003,
/// 3 passes) and `default` (qemd's default operator).
pub fn report_methods() -> Vec<TableMethod> {
    vec![
        TableMethod::new(FAITHFUL, Params::paper()),
        TableMethod::new(
            BILATERAL,
            Params {
                method: Method::Bilateral,
                iterations: 3,
                ..Params::default()
            },
        ),
        TableMethod::new(DEFAULT, Params::default()),
    ]
}

/// The colour of a method in every chart of the report.
pub fn method_colour(name: &str) -> [u8; 3] {
    match name {
        NOISY => colours::NOISY,
        FAITHFUL => colours::FAITHFUL,
        BILATERAL => colours::BILATERAL,
        DEFAULT => colours::DEFAULT,
        _ => colours::OTHER,
    }
}

/// A readable label for a row name.
pub fn label(name: &str) -> &str {
    match name {
        NOISY => "noisy input",
        FAITHFUL => "faithful",
        BILATERAL => "bilateral",
        DEFAULT => "qemd default",
        other => other,
    }
}
