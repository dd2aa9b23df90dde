//! The one parameter spec: everything a run computes with, but its paths and formats.
//!
//! A run is asked for in four ways — `qemd denoise` flags, a job's JSON body, the synchronous
//! endpoint's query string, and the Python keywords — and all of them deserialise into one
//! [`SpecOverlay`]: every field optional, named as in [`Params`] plus `paper`, `outliers`,
//! `outlier_alpha` and `classes`. [`SpecOverlay::resolve`] lays it over the defaults (or over
//! [`Params::paper`] when `paper` is set) and [`DenoiseSpec::validate`]s the result, so each
//! default and each range check exists once:
//!
//! - operator defaults: [`Params::default`] and [`Params::paper`];
//! - what the data decides (filter, updates, cycles, `sigma_r`): [`Params::schedule`], at run
//!   time, never at parse time (a bilateral run asked for from the CLI or the API stores
//!   `iterations: 0` and runs three passes either way);
//! - the outlier threshold: [`DEFAULT_OUTLIER_ALPHA`], which a configuration may replace
//!   (`outlier_alpha` in `config/default.toml`), passed to [`SpecOverlay::resolve`];
//! - ranges: [`Params::validate`] and [`DenoiseSpec::validate`].
//!
//! The field names callers may use come from serde itself ([`SpecOverlay::fields`]), so the
//! OpenAPI schema, the 422 texts and the query-string parser cannot drift from the struct.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use super::OutlierMode;
use super::classes::ClassList;
use crate::denoise::{
    DenoiseError, Method, NormalWeighting, Params, Planes, SensorOrigin, SolveKind,
};

/// The default outlier threshold: mean k-NN distance above mean + 2σ over the cloud.
pub const DEFAULT_OUTLIER_ALPHA: f64 = 2.0;

/// A parameter the spec refuses, named as the spec spells it (`sigma_r`, `outlier_alpha`).
#[derive(Debug, Error, Clone, PartialEq)]
#[error("invalid parameter {field}: {detail}")]
pub struct SpecError {
    /// Field name (snake case: the JSON field, the query parameter, the Python keyword; the CLI
    /// flag is the same with `-` for `_`).
    pub field: &'static str,
    /// What is wrong.
    pub detail: String,
}

impl From<DenoiseError> for SpecError {
    fn from(e: DenoiseError) -> SpecError {
        match e {
            DenoiseError::Param { name, detail } => SpecError {
                field: name,
                detail,
            },
            other => SpecError {
                field: "params",
                detail: other.to_string(),
            },
        }
    }
}

/// What a run computes: the operator's parameters and what to do with outliers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DenoiseSpec {
    /// Operator parameters.
    pub params: Params,
    /// Outlier handling.
    #[serde(default)]
    pub outliers: OutlierMode,
    /// Outlier threshold in standard deviations above the mean.
    #[serde(default = "default_alpha")]
    pub outlier_alpha: f64,
    /// Point clouds: only points of these classes move (`--classes`); `None`: every point but
    /// LAS noise (classes 7 and 18). LAS withheld points never move.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub classes: Option<ClassList>,
}

fn default_alpha() -> f64 {
    DEFAULT_OUTLIER_ALPHA
}

impl Default for DenoiseSpec {
    fn default() -> DenoiseSpec {
        DenoiseSpec {
            params: Params::default(),
            outliers: OutlierMode::Off,
            outlier_alpha: DEFAULT_OUTLIER_ALPHA,
            classes: None,
        }
    }
}

impl DenoiseSpec {
    /// Checks every range; call before any I/O.
    ///
    /// # Errors
    /// [`SpecError`] naming the first bad field.
    pub fn validate(&self) -> Result<(), SpecError> {
        self.params.validate()?;
        validate_alpha(self.outlier_alpha)
    }

    /// This spec for an input of `format`: a sensor origin left to the input
    /// ([`SensorOrigin::Auto`]) becomes `0,0,0` for formats stored in their sensor's frame
    /// ([`crate::io::Format::sensor_frame`]) and `none` for the others, so a run, its report and
    /// a frozen scale-out job state the beams in force.
    /// (A job with a trajectory gets its beams from it instead: see [`super::Job::trajectory`].)
    pub fn for_format(&self, format: crate::io::Format) -> DenoiseSpec {
        let mut spec = self.clone();
        if spec.params.sensor_origin == SensorOrigin::Auto {
            spec.params.sensor_origin = if format.sensor_frame() {
                SensorOrigin::At([0.0; 3])
            } else {
                SensorOrigin::Off
            };
        }
        spec
    }

    /// Refuses, for a run in mesh mode (`mesh`), the options that apply to point clouds only:
    /// outlier handling and written normals (a mesh's stored normals are recomputed from its
    /// faces instead).
    ///
    /// # Errors
    /// [`SpecError`] naming `outliers` or `write_normals`.
    pub fn check_mesh(&self, mesh: bool) -> Result<(), SpecError> {
        let refuse = |field, extra: &str| {
            Err(SpecError {
                field,
                detail: format!("applies to point clouds, not meshes{extra}"),
            })
        };
        if !mesh {
            Ok(())
        } else if self.outliers != OutlierMode::Off {
            refuse("outliers", "")
        } else if self.classes.is_some() {
            refuse("classes", "")
        } else if self.params.write_normals {
            refuse(
                "write_normals",
                " (a mesh's stored normals are recomputed from its faces)",
            )
        } else {
            Ok(())
        }
    }
}

/// The outlier threshold's range (also the configuration's).
///
/// # Errors
/// [`SpecError`] on a negative or non-finite α.
pub fn validate_alpha(alpha: f64) -> Result<(), SpecError> {
    if alpha.is_finite() && alpha >= 0.0 {
        Ok(())
    } else {
        Err(SpecError {
            field: "outlier_alpha",
            detail: format!("must be finite and ≥ 0, got {alpha}"),
        })
    }
}

/// A request's choices, each optional (on the command line the booleans are the flags
/// `--paper`, `--no-volume`, `--no-guard` and `--write-normals`: present sets the field, absent
/// leaves it unset): the CLI flags (`qemd denoise --knn 8`), a job's `params`
/// object, the synchronous endpoint's query string and the Python keywords all parse into it.
/// Unset fields keep the base ([`Params::default`], or [`Params::paper`] with `paper`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
#[serde(deny_unknown_fields)]
pub struct SpecOverlay {
    /// The paper's Algorithm 1 exactly (tangent planes, raw normals, one plain-solve pass); the
    /// other fields still override it.
    #[cfg_attr(
        feature = "cli",
        arg(long, num_args = 0, default_missing_value = "true")
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub paper: Option<bool>,
    /// Denoising method (default qem).
    #[cfg_attr(feature = "cli", arg(long, value_enum))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub method: Option<Method>,
    /// face (default: filtered face planes; curvature-corrected tangent planes on clouds) or
    /// tangent (the paper: vertex tangent planes over k-rings / k-NN lists).
    #[cfg_attr(feature = "cli", arg(long, value_enum))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub planes: Option<Planes>,
    /// Normal-filter iterations per cycle (0: raw normals). Default 10 on meshes, 3 on clouds.
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub filter: Option<usize>,
    /// QEM updates per cycle. Default 5 on meshes, 2 on clouds.
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub updates: Option<usize>,
    /// Relative step penalty of the damped solve (default 0.5).
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mu: Option<f64>,
    /// Lower bound of the normal filter's range width (default 0.35 meshes, 0.2 clouds).
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_r: Option<f64>,
    /// Restore the enclosed volume of closed meshes (default true; the CLI's --no-volume
    /// clears it).
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "no-volume",
            num_args = 0,
            default_missing_value = "false",
            help = "Meshes: do not restore the enclosed volume (by default a closed mesh gets \
                    its input volume back by a final offset along the normals)"
        )
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub volume: Option<bool>,
    /// Clouds: classify every neighbourhood and move only where it shows a surface or a line,
    /// with plane votes weighted by agreement and every step bounded by the local noise (default
    /// true; the CLI's --no-guard clears it and moves every point; --paper implies that).
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "no-guard",
            num_args = 0,
            default_missing_value = "false",
            help = "Clouds: turn the guard off and move every point (by default each \
                    neighbourhood is classified and only surfaces and lines move, every step \
                    bounded by the local noise; --paper turns it off too)"
        )
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub guard: Option<bool>,
    /// Hard cap on any point's displacement, in the input's units (metres for LiDAR). Default:
    /// none beyond the guarded operator's own bounds: 3 × the local noise (1 × at edges and
    /// lines) and 0.25 × the point's own k-NN radius. Every cap holds in the written file: a
    /// coordinate the output stores coarsely (float32, LAS scale) is rounded towards the input's
    /// where rounding to nearest would lengthen the move.
    #[cfg_attr(feature = "cli", arg(long, value_name = "DISTANCE"))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_move: Option<f64>,
    /// Point mode: the farthest a neighbour may be, in the input's units (metres for LiDAR);
    /// lists hold the k nearest points within it (PCL's and Open3D's hybrid search), and a point
    /// with fewer than 8 that near keeps its position (counted as isolated). Default: none beyond
    /// the cloud's isolation radius (32 typical k-NN radii).
    #[cfg_attr(feature = "cli", arg(long, value_name = "DISTANCE"))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub radius: Option<f64>,
    /// k-ring size of tangent planes in mesh mode, the vertex itself included (default 2).
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rings: Option<usize>,
    /// Neighbourhood size in point mode (the point itself included); forces point mode. Default
    /// 16 on point clouds; meshes run on k-rings unless it is given.
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub knn: Option<usize>,
    /// Mesh vertex normals (default area).
    #[cfg_attr(feature = "cli", arg(long, value_enum))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normals: Option<NormalWeighting>,
    /// How the quadric minimiser is found (default damped).
    #[cfg_attr(feature = "cli", arg(long, value_enum))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub solve: Option<SolveKind>,
    /// Relative eigenvalue cut-off of the robust solve (default 0.01).
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub eps: Option<f64>,
    /// Step penalty of the regularised solve (default 0.1).
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lambda: Option<f64>,
    /// Cycles (QEM: normal filter then updates; default 0, which chooses from the data on meshes
    /// and is 1 on clouds) or passes (bilateral, 0 chooses 3).
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub iterations: Option<usize>,
    /// Statistical outliers: leave them (off, the default), flag them (classify: LAS class 7, or
    /// a `noise` property in PLY, PCD and text; flagged points keep their input position), or
    /// remove them.
    #[cfg_attr(feature = "cli", arg(long, value_enum))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outliers: Option<OutlierMode>,
    /// Outlier threshold: mean k-NN distance above mean + ALPHA·σ (default from the
    /// configuration: 2).
    #[cfg_attr(feature = "cli", arg(long))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outlier_alpha: Option<f64>,
    /// Point clouds: move only the points of these classes, e.g. `2,6` or `1-6` (LAS
    /// classification, or a `class` or `label` field in PLY, PCD and text); the others keep their
    /// position but still serve as neighbours. Default: every point moves, except on LAS input
    /// the noise classes 7 and 18 (name them, or give `0-255`, to move them); LAS withheld
    /// points always stay.
    #[cfg_attr(
        feature = "cli",
        arg(long, value_name = "CODES", value_parser = super::classes::parse)
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub classes: Option<ClassList>,
    /// Point clouds: write each point's normal (oriented towards +z), surface variation and
    /// structure class as extra fields (PLY nx ny nz curvature structure, PCD normal_x …, LAS
    /// extra bytes NormalX …); fields of those names already in the input are overwritten.
    /// Default off: the output keeps the input's schema.
    #[cfg_attr(
        feature = "cli",
        arg(long = "write-normals", num_args = 0, default_missing_value = "true")
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub write_normals: Option<bool>,
    /// Point clouds: the sensor's position, X,Y,Z in the input's coordinates (a sweep or a
    /// terrestrial station): each return's beam runs from it, and the default operator fits
    /// neighbourhoods along the beams and moves each return only along its own. `auto` (the
    /// default): KITTI and nuScenes sweeps, stored in their sensor's frame, have it at 0,0,0;
    /// other inputs have no beams. `none`: no beams.
    #[cfg_attr(feature = "cli", arg(long, value_name = "X,Y,Z"))]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sensor_origin: Option<SensorOrigin>,
}

impl SpecOverlay {
    /// The spec these choices select over the defaults, with `alpha` as the outlier threshold
    /// unless one is given; validated.
    ///
    /// # Errors
    /// [`SpecError`] naming the first bad field.
    pub fn resolve(&self, alpha: f64) -> Result<DenoiseSpec, SpecError> {
        let spec = self.apply(alpha);
        spec.validate()?;
        Ok(spec)
    }

    /// The spec these choices select, not yet validated.
    pub fn apply(&self, alpha: f64) -> DenoiseSpec {
        let mut p = if self.paper == Some(true) {
            Params::paper()
        } else {
            Params::default()
        };
        fn set<T: Copy>(slot: &mut T, v: Option<T>) {
            if let Some(v) = v {
                *slot = v;
            }
        }
        set(&mut p.method, self.method);
        set(&mut p.planes, self.planes);
        set(&mut p.mu, self.mu);
        set(&mut p.volume, self.volume);
        set(&mut p.guard, self.guard);
        set(&mut p.write_normals, self.write_normals);
        set(&mut p.sensor_origin, self.sensor_origin);
        set(&mut p.rings, self.rings);
        set(&mut p.normals, self.normals);
        set(&mut p.solve, self.solve);
        set(&mut p.eps, self.eps);
        set(&mut p.lambda, self.lambda);
        set(&mut p.iterations, self.iterations);
        // Fields the defaults leave to the data: set, they replace the data's choice.
        for (slot, v) in [(&mut p.filter, self.filter), (&mut p.updates, self.updates)] {
            if v.is_some() {
                *slot = v;
            }
        }
        if self.knn.is_some() {
            p.knn = self.knn;
        }
        if self.sigma_r.is_some() {
            p.sigma_r = self.sigma_r;
        }
        if self.max_move.is_some() {
            p.max_move = self.max_move;
        }
        if self.radius.is_some() {
            p.radius = self.radius;
        }
        DenoiseSpec {
            params: p,
            outliers: self.outliers.unwrap_or_default(),
            outlier_alpha: self.outlier_alpha.unwrap_or(alpha),
            classes: self.classes.clone(),
        }
    }

    /// Lays `other` over these choices: each field `other` sets wins.
    ///
    /// # Errors
    /// The name of a field both set to different values (a request that says two things).
    pub fn merge(mut self, other: SpecOverlay) -> Result<SpecOverlay, &'static str> {
        macro_rules! take {
            ($($f:ident),*) => {$(
                match (&self.$f, other.$f) {
                    (Some(a), Some(b)) if *a != b => return Err(stringify!($f)),
                    (_, Some(b)) => self.$f = Some(b),
                    _ => {}
                }
            )*};
        }
        take!(
            paper,
            method,
            planes,
            filter,
            updates,
            mu,
            sigma_r,
            volume,
            guard,
            max_move,
            radius,
            rings,
            knn,
            normals,
            solve,
            eps,
            lambda,
            iterations,
            outliers,
            outlier_alpha,
            classes,
            write_normals,
            sensor_origin
        );
        Ok(self)
    }

    /// Every field name a request may use, in declaration order, as serde reads them.
    pub fn fields() -> &'static [&'static str] {
        fields_of::<SpecOverlay>()
    }
}

/// The field names serde's derive gives a struct (it passes them to `deserialize_struct`).
fn fields_of<T: serde::de::DeserializeOwned>() -> &'static [&'static str] {
    use serde::de::{self, Visitor};

    #[derive(Debug)]
    struct Found(&'static [&'static str]);
    impl std::fmt::Display for Found {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str("field names found")
        }
    }
    impl std::error::Error for Found {}
    impl de::Error for Found {
        fn custom<M: std::fmt::Display>(_: M) -> Found {
            Found(&[])
        }
    }

    struct Probe;
    impl<'de> de::Deserializer<'de> for Probe {
        type Error = Found;
        fn deserialize_any<V: Visitor<'de>>(self, _: V) -> Result<V::Value, Found> {
            Err(Found(&[]))
        }
        fn deserialize_struct<V: Visitor<'de>>(
            self,
            _: &'static str,
            fields: &'static [&'static str],
            _: V,
        ) -> Result<V::Value, Found> {
            Err(Found(fields))
        }
        serde::forward_to_deserialize_any! {
            bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf
            option unit unit_struct newtype_struct seq tuple tuple_struct map enum identifier
            ignored_any
        }
    }

    match T::deserialize(Probe) {
        Err(Found(fields)) => fields,
        Ok(_) => &[],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_are_the_params_and_the_outlier_options() {
        // Every field of Params serialises when set (`write_normals` only when on).
        let all = Params {
            write_normals: true,
            sensor_origin: SensorOrigin::At([0.0; 3]),
            ..Params::default()
        };
        let Ok(serde_json::Value::Object(params)) = serde_json::to_value(all) else {
            panic!("Params is not an object");
        };
        let mut want: Vec<&str> = params.keys().map(String::as_str).collect();
        want.extend(["paper", "outliers", "outlier_alpha", "classes"]);
        want.sort_unstable();
        let mut got = SpecOverlay::fields().to_vec();
        got.sort_unstable();
        assert_eq!(got, want);
    }

    #[cfg(feature = "cli")]
    #[test]
    fn help_states_the_defaults_of_params() {
        // The flags are optional, so clap cannot show a default; their help says it in words,
        // and this keeps the words equal to `Params::default()`.
        use clap::Args as _;
        let cmd = SpecOverlay::augment_args(clap::Command::new("t"));
        let Ok(serde_json::Value::Object(d)) = serde_json::to_value(Params::default()) else {
            panic!("Params is not an object");
        };
        for field in ["method", "mu", "rings", "normals", "solve", "eps", "lambda"] {
            let arg = cmd
                .get_arguments()
                .find(|a| a.get_id() == field)
                .unwrap_or_else(|| panic!("{field} is a flag"));
            let help = arg.get_help().map(|h| h.to_string()).unwrap_or_default();
            let value = match &d[field] {
                serde_json::Value::String(s) => s.clone(),
                v => v.to_string(),
            };
            assert!(
                help.contains(&format!("default {value}")),
                "{field}: `{help}` does not say `default {value}`"
            );
        }
    }

    #[test]
    fn empty_overlay_is_the_default_spec() {
        assert_eq!(
            SpecOverlay::default().resolve(DEFAULT_OUTLIER_ALPHA),
            Ok(DenoiseSpec::default())
        );
    }

    #[test]
    fn paper_is_a_base_the_other_fields_override() {
        let o = SpecOverlay {
            paper: Some(true),
            mu: Some(0.25),
            ..SpecOverlay::default()
        };
        let s = o.resolve(1.0).unwrap();
        assert_eq!(
            s.params,
            Params {
                mu: 0.25,
                ..Params::paper()
            }
        );
        assert_eq!(s.outlier_alpha, 1.0);
        // `paper: false` is the default base.
        let o = SpecOverlay {
            paper: Some(false),
            ..SpecOverlay::default()
        };
        assert_eq!(o.apply(2.0).params, Params::default());
    }

    #[test]
    fn issue10_bilateral_iterations_are_left_to_the_schedule() {
        let o = SpecOverlay {
            method: Some(Method::Bilateral),
            ..SpecOverlay::default()
        };
        let p = o.resolve(2.0).unwrap().params;
        assert_eq!(p.iterations, 0);
        assert_eq!(p.schedule(true).cycles, 3);
        assert_eq!(p.schedule(false).cycles, 3);
    }

    #[test]
    fn errors_name_the_field() {
        let o = SpecOverlay {
            sigma_r: Some(5.0),
            ..SpecOverlay::default()
        };
        assert_eq!(o.resolve(2.0).unwrap_err().field, "sigma_r");
        let o = SpecOverlay {
            outlier_alpha: Some(-1.0),
            ..SpecOverlay::default()
        };
        let e = o.resolve(2.0).unwrap_err();
        assert_eq!(e.field, "outlier_alpha");
        assert_eq!(
            e.to_string(),
            "invalid parameter outlier_alpha: must be finite and ≥ 0, got -1"
        );
        let e: Result<SpecOverlay, _> = serde_json::from_str(r#"{"knnn": 3}"#);
        let msg = e.unwrap_err().to_string();
        assert!(msg.contains("unknown field `knnn`") && msg.contains("outlier_alpha"));
    }

    #[test]
    fn merge_refuses_two_answers() {
        let a = SpecOverlay {
            knn: Some(8),
            ..SpecOverlay::default()
        };
        let b = SpecOverlay {
            knn: Some(8),
            eps: Some(0.5),
            ..SpecOverlay::default()
        };
        let m = a.clone().merge(b).unwrap();
        assert_eq!((m.knn, m.eps), (Some(8), Some(0.5)));
        let c = SpecOverlay {
            knn: Some(9),
            ..SpecOverlay::default()
        };
        assert_eq!(a.merge(c), Err("knn"));
    }

    #[test]
    fn merge_takes_every_field() {
        // An overlay with every field set (the defaults' values, nulls made numbers) merged
        // over an empty one comes back whole: a field left out of `merge` would be dropped.
        let all = Params {
            write_normals: true,
            sensor_origin: SensorOrigin::At([0.0; 3]),
            ..Params::default()
        };
        let Ok(serde_json::Value::Object(mut m)) = serde_json::to_value(all) else {
            panic!("Params is not an object");
        };
        for v in m.values_mut() {
            if v.is_null() {
                *v = serde_json::json!(3);
            }
        }
        m.insert("paper".into(), serde_json::json!(true));
        m.insert("outliers".into(), serde_json::json!("remove"));
        m.insert("outlier_alpha".into(), serde_json::json!(1.5));
        m.insert("classes".into(), serde_json::json!("2,6"));
        let full: SpecOverlay = serde_json::from_value(serde_json::Value::Object(m)).unwrap();
        let Ok(serde_json::Value::Object(set)) = serde_json::to_value(&full) else {
            panic!("SpecOverlay is not an object");
        };
        assert_eq!(set.len(), SpecOverlay::fields().len());
        assert_eq!(SpecOverlay::default().merge(full.clone()), Ok(full.clone()));
        assert_eq!(full.clone().merge(SpecOverlay::default()), Ok(full));
    }

    #[test]
    fn stored_specs_keep_loading() {
        // The shape jobs were stored in before the spec existed: params, outliers, alpha.
        let s: DenoiseSpec = serde_json::from_str(
            r#"{"params": {"method": "bilateral", "iterations": 3}, "outliers": "classify",
                "outlier_alpha": 2.5}"#,
        )
        .unwrap();
        assert_eq!(s.params.iterations, 3);
        assert_eq!(s.outliers, OutlierMode::Classify);
        assert_eq!(s.outlier_alpha, 2.5);
        assert!(!s.params.write_normals);
    }

    #[test]
    fn issue9_write_normals_is_off_by_default_and_stored_only_when_on() {
        let off = SpecOverlay::default().resolve(2.0).unwrap();
        assert!(!off.params.write_normals);
        // A spec without it serialises as before (stored jobs, reports, frozen scale-out jobs).
        let text = serde_json::to_string(&off).unwrap();
        assert!(!text.contains("write_normals"), "{text}");
        let on: SpecOverlay = serde_json::from_str(r#"{"write_normals": true}"#).unwrap();
        let on = on.resolve(2.0).unwrap();
        assert!(on.params.write_normals);
        let back: DenoiseSpec = serde_json::from_str(&serde_json::to_string(&on).unwrap()).unwrap();
        assert_eq!(back, on);
    }
}
