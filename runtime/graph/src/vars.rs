//! Variables: `${name}` in strings, replaced by the value declared under `inputs:` or given
//! on the command line.

use std::collections::BTreeMap;

use serde_json::Value;

/// Why a string could not be substituted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum VarProblem {
    /// `${name}` with no such variable.
    Unknown(String),
    /// `${` without `}`.
    Unclosed,
}

/// Replaces every `${name}` in `text`. Text around references is kept as is; the values
/// are not scanned again.
pub(crate) fn substitute(text: &str, vars: &BTreeMap<String, String>) -> Result<String, VarProblem> {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(start) = rest.find("${") {
        out.push_str(&rest[..start]);
        let after = &rest[start + 2..];
        let end = after.find('}').ok_or(VarProblem::Unclosed)?;
        let name = &after[..end];
        let value = vars.get(name).ok_or_else(|| VarProblem::Unknown(name.to_owned()))?;
        out.push_str(value);
        rest = &after[end + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

/// The variable name when `text` is exactly one reference, `${name}`.
fn whole_reference(text: &str) -> Option<&str> {
    let name = text.strip_prefix("${")?.strip_suffix('}')?;
    (!name.contains('}')).then_some(name)
}

/// Substitutes in every string of `value` (mapping keys are left alone). A string that was
/// exactly one reference becomes a number or a boolean when the variable's value reads as
/// one in YAML, so `count: "${count}"` can feed an integer parameter.
///
/// # Errors
/// The path (below `value`) of the first string that fails, and why.
pub(crate) fn substitute_value(
    value: &mut Value,
    vars: &BTreeMap<String, String>,
) -> Result<(), (Vec<String>, VarProblem)> {
    match value {
        Value::String(text) => {
            let substituted = substitute(text, vars).map_err(|problem| (Vec::new(), problem))?;
            *value = match whole_reference(text) {
                Some(_) => typed_scalar(&substituted).unwrap_or(Value::String(substituted)),
                None => Value::String(substituted),
            };
            Ok(())
        }
        Value::Array(items) => items.iter_mut().enumerate().try_for_each(|(index, item)| {
            substitute_value(item, vars).map_err(|(mut path, problem)| {
                path.insert(0, index.to_string());
                (path, problem)
            })
        }),
        Value::Object(map) => map.iter_mut().try_for_each(|(key, item)| {
            substitute_value(item, vars).map_err(|(mut path, problem)| {
                path.insert(0, key.clone());
                (path, problem)
            })
        }),
        Value::Null | Value::Bool(_) | Value::Number(_) => Ok(()),
    }
}

/// `text` as a YAML number or boolean, if it is one.
fn typed_scalar(text: &str) -> Option<Value> {
    match serde_saphyr::from_str::<Value>(text) {
        Ok(typed @ (Value::Number(_) | Value::Bool(_))) => Some(typed),
        _ => None,
    }
}
