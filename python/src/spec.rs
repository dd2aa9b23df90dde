//! Python keywords → the one parameter spec ([`SpecOverlay`]).
//!
//! Each keyword is deserialised by serde into a one-field [`SpecOverlay`] (so its name, its type
//! and its enum spellings are the spec's, and an unknown name gets serde's "unknown field"
//! message listing the known ones), the overlays are merged, and [`SpecOverlay::resolve`] checks
//! the ranges with the messages the CLI and the API give. Python values go through a small serde
//! deserializer rather than JSON, so a `float("nan")` reaches the spec's own range check. The
//! pytest suite (`python/tests`) tests these messages against the CLI's.

use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};
use qem_denoise::pipeline::{DEFAULT_OUTLIER_ALPHA, DenoiseSpec, SpecOverlay};
use serde::Deserialize as _;
use serde::de::value::{Error as DeError, MapDeserializer, SeqDeserializer, StringDeserializer};
use serde::de::{self, IntoDeserializer, Visitor};

/// A keyword's value, as the spec may read it.
#[derive(Debug, Clone)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    UInt(u64),
    Float(f64),
    Str(String),
    /// A list or tuple of such values (a sensor origin's `[x, y, z]`).
    Seq(Vec<Value>),
}

impl Value {
    /// Reads a Python value; any other type is refused with `Err(type name)`.
    pub fn from_py(v: &Bound<'_, PyAny>) -> Result<Value, String> {
        if v.is_none() {
            Ok(Value::None)
        } else if let Ok(b) = v.cast::<PyBool>() {
            Ok(Value::Bool(b.is_true()))
        } else if let Ok(s) = v.cast::<PyString>() {
            Ok(Value::Str(s.to_string()))
        } else if v.is_instance_of::<PyInt>() || v.hasattr("__index__").unwrap_or(false) {
            // Python ints and integer scalars such as numpy.int64.
            match v.extract::<i64>() {
                Ok(i) => Ok(Value::Int(i)),
                Err(_) => v
                    .extract::<u64>()
                    .map(Value::UInt)
                    .map_err(|_| type_name(v)),
            }
        } else if v.is_instance_of::<PyFloat>() || v.hasattr("__float__").unwrap_or(false) {
            // Python floats and float scalars such as numpy.float32.
            v.extract::<f64>()
                .map(Value::Float)
                .map_err(|_| type_name(v))
        } else if v.is_instance_of::<PyList>() || v.is_instance_of::<PyTuple>() {
            let items: Vec<Bound<'_, PyAny>> = v.extract().map_err(|_| type_name(v))?;
            items
                .iter()
                .map(|x| match Value::from_py(x)? {
                    // One level: the spec has no field of nested lists.
                    Value::Seq(_) => Err(type_name(x)),
                    one => Ok(one),
                })
                .collect::<Result<_, _>>()
                .map(Value::Seq)
        } else {
            Err(type_name(v))
        }
    }
}

fn type_name(v: &Bound<'_, PyAny>) -> String {
    v.get_type()
        .name()
        .map_or_else(|_| "object".to_string(), |n| n.to_string())
}

impl<'de> de::Deserializer<'de> for Value {
    type Error = DeError;

    fn deserialize_any<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match self {
            Value::None => v.visit_unit(),
            Value::Bool(b) => v.visit_bool(b),
            Value::Int(i) => v.visit_i64(i),
            Value::UInt(u) => v.visit_u64(u),
            Value::Float(f) => v.visit_f64(f),
            Value::Str(s) => v.visit_string(s),
            Value::Seq(s) => v.visit_seq(SeqDeserializer::new(s.into_iter())),
        }
    }

    fn deserialize_option<V: Visitor<'de>>(self, v: V) -> Result<V::Value, DeError> {
        match self {
            Value::None => v.visit_none(),
            other => v.visit_some(other),
        }
    }

    fn deserialize_enum<V: Visitor<'de>>(
        self,
        name: &'static str,
        variants: &'static [&'static str],
        v: V,
    ) -> Result<V::Value, DeError> {
        match self {
            Value::Str(s) => {
                let d: StringDeserializer<DeError> = s.into_deserializer();
                d.deserialize_enum(name, variants, v)
            }
            other => other.deserialize_any(v),
        }
    }

    serde::forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf
        unit unit_struct newtype_struct seq tuple tuple_struct map struct identifier ignored_any
    }
}

impl<'de> IntoDeserializer<'de, DeError> for Value {
    type Deserializer = Value;
    fn into_deserializer(self) -> Value {
        self
    }
}

/// The spec the keywords `params` ask for, validated; `Err` holds the one-line message.
pub fn spec_of(params: &[(String, Value)]) -> Result<DenoiseSpec, String> {
    let mut overlay = SpecOverlay::default();
    for (name, value) in params {
        let one = MapDeserializer::new(std::iter::once((name.as_str(), value.clone())));
        let field = SpecOverlay::deserialize(one).map_err(|e| {
            let msg = e.to_string();
            if msg.starts_with("unknown field") {
                msg
            } else {
                format!("invalid parameter {name}: {msg}")
            }
        })?;
        overlay = overlay
            .merge(field)
            .map_err(|f| format!("invalid parameter {f}: given twice"))?;
    }
    overlay
        .resolve(DEFAULT_OUTLIER_ALPHA)
        .map_err(|e| e.to_string())
}

/// Keywords split into the spec's (read as values) and the function's own options.
pub type Keywords<'py> = (Vec<(String, Value)>, Vec<(String, Bound<'py, PyAny>)>);

/// The keywords of `kwargs` but those in `own` (the function's own options, returned apart),
/// each read as a [`Value`].
pub fn split_kwargs<'py>(
    kwargs: Option<&Bound<'py, PyDict>>,
    own: &[&str],
) -> Result<Keywords<'py>, String> {
    let mut params = Vec::new();
    let mut options = Vec::new();
    let Some(kwargs) = kwargs else {
        return Ok((params, options));
    };
    for (k, v) in kwargs.iter() {
        let name: String = k.extract().map_err(|e: PyErr| e.to_string())?;
        if own.contains(&name.as_str()) {
            options.push((name, v));
            continue;
        }
        let value = Value::from_py(&v).map_err(|t| {
            format!("invalid parameter {name}: a number, a bool, a string, a list of numbers or None, not {t}")
        })?;
        params.push((name, value));
    }
    Ok((params, options))
}
