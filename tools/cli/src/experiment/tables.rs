//! The tables of an experiment's eval results, as markdown, and their place in a file
//! between two markers.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use anyhow::{Context, Result, bail};
use serde::Deserialize;

use super::file::{Ratio, RatioForm, Sequences, Table};

/// What the tables read of `gprflow eval --format json`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct EvalResult {
    /// ATE without alignment.
    pub ate: Option<Rmse>,
    /// Registrations against the truth's relative motion.
    #[serde(default)]
    pub registration: Option<RegistrationResult>,
}

/// A statistic's RMSE and count.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct Rmse {
    /// Root mean square, m.
    pub rmse: f64,
    /// Number of values.
    pub count: usize,
}

/// What the tables read of a run's registration error.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct RegistrationResult {
    /// Along-track error, m.
    pub along_track: Rmse,
}

/// One world's eval results: per sequence (in order), per model.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldResults {
    /// The world's name (a column).
    pub name: String,
    /// Per sequence: its label and each model's result.
    pub sequences: Vec<(String, BTreeMap<String, EvalResult>)>,
}

/// Over which sequences the tables are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SequenceSet {
    /// The world's run and its repeats, or the repeats alone.
    pub sequences: Sequences,
    /// Repeats per world.
    pub repeats: u32,
}

/// Every table of `tables`, blank lines between them.
///
/// # Errors
/// A result the tables need is missing.
pub fn render(tables: &[Table], set: SequenceSet, worlds: &[WorldResults]) -> Result<String> {
    let parts: Vec<String> = tables
        .iter()
        .map(|t| match t {
            Table::Registration { models, labels } => registration_table(models, labels, worlds),
            Table::Ate { models, ratio } => ate_table(models, ratio.as_ref(), set, worlds),
        })
        .collect::<Result<_>>()?;
    Ok(parts.join("\n\n"))
}

fn result<'a>(world: &'a WorldResults, sequence: usize, model: &str) -> Result<&'a EvalResult> {
    let (label, results) = world
        .sequences
        .get(sequence)
        .with_context(|| format!("{}: no sequence {sequence}", world.name))?;
    results
        .get(model)
        .with_context(|| format!("{label} {model}: no eval result"))
}

fn header(first: &str, worlds: &[WorldResults], last: Option<&str>) -> [String; 2] {
    let names: Vec<&str> = worlds.iter().map(|w| w.name.as_str()).chain(last).collect();
    [
        format!("| {first} | {} |", names.join(" | ")),
        format!("|---|{}", "---|".repeat(names.len())),
    ]
}

/// Registration error on each world's run (its first sequence), per model, and combined over
/// the worlds (the RMS of all their registrations).
fn registration_table(models: &[String], labels: &BTreeMap<String, String>, worlds: &[WorldResults]) -> Result<String> {
    let mut lines = vec![
        "Registration error (RMSE of the along-track error against the truth, cm; pairs from the oracle association; n = registrations):".to_owned(),
        String::new(),
    ];
    lines.extend(header("model", worlds, Some("combined")));
    for model in models {
        let (mut cells, mut square_sum, mut count) = (Vec::new(), 0.0, 0);
        for world in worlds {
            match result(world, 0, model)?.registration {
                None => cells.push("-".to_owned()),
                Some(RegistrationResult { along_track: a }) => {
                    cells.push(format!("{:.2} (n={})", 100.0 * a.rmse, a.count));
                    square_sum += a.rmse.powi(2) * count_f64(a.count);
                    count += a.count;
                }
            }
        }
        let combined = if count > 0 {
            format!("{:.2}", 100.0 * (square_sum / count_f64(count)).sqrt())
        } else {
            "-".to_owned()
        };
        let label = labels.get(model).unwrap_or(model);
        lines.push(format!("| {label} | {} | {combined} |", cells.join(" | ")));
    }
    Ok(lines.join("\n"))
}

/// ATE per model and world over the world's sequences, and the ratio row.
fn ate_table(models: &[String], ratio: Option<&Ratio>, set: SequenceSet, worlds: &[WorldResults]) -> Result<String> {
    let repeats = set.repeats;
    let (title, single) = match set.sequences {
        Sequences::RunAndRepeats if repeats == 0 => (
            "ATE (RMSE of the final trajectory against the truth, m, no alignment) each world's run:".to_owned(),
            true,
        ),
        Sequences::RunAndRepeats => (
            format!(
                "ATE (RMSE of the final trajectory against the truth, m, no alignment) over {} sequences per world, the world's run and its repeats 1-{repeats} with fresh sensor noise: mean [min, max]:",
                repeats + 1
            ),
            false,
        ),
        Sequences::Repeats => (
            format!(
                "ATE over {repeats} repeats (fresh sensor noise, same world and path; m, no alignment): mean [min, max]"
            ),
            false,
        ),
    };
    let mut lines = vec![title, String::new()];
    lines.extend(header("run", worlds, None));
    for model in models {
        let cells = worlds
            .iter()
            .map(|w| {
                let v = ates(w, model)?;
                Ok(if single { format!("{:.3}", v[0]) } else { spread(&v, 3) })
            })
            .collect::<Result<Vec<_>>>()?;
        lines.push(format!("| {model} | {} |", cells.join(" | ")));
    }
    if let Some(r) = ratio {
        lines.push(ratio_row(r, worlds)?);
    }
    Ok(lines.join("\n"))
}

fn ratio_row(r: &Ratio, worlds: &[WorldResults]) -> Result<String> {
    let factor = within_factor(r.within_percent);
    let p = r.within_percent;
    let mut cells = Vec::new();
    for world in worlds {
        let (model, reference) = (ates(world, &r.model)?, ates(world, &r.reference)?);
        let n = model.len();
        cells.push(match r.form {
            RatioForm::OfMeans => {
                let within = model.iter().zip(&reference).filter(|&(a, b)| *a <= factor * b).count();
                format!(
                    "{:.2}; within {p} % in {within} of {n}",
                    mean(&model) / mean(&reference)
                )
            }
            RatioForm::OfRatios => {
                let ratios: Vec<f64> = model.iter().zip(&reference).map(|(a, b)| a / b).collect();
                let within = ratios.iter().filter(|&&x| x <= factor).count();
                format!("{}, within {p} %: {within} of {n}", spread(&ratios, 2))
            }
        });
    }
    let label = match r.form {
        RatioForm::OfMeans => format!("{} / {} (of the means; per sequence)", r.model, r.reference),
        RatioForm::OfRatios => format!("{} / {}", r.model, r.reference),
    };
    Ok(format!("| {label} | {} |", cells.join(" | ")))
}

/// `1 + percent / 100` (15 gives the double nearest 1.15).
fn within_factor(percent: u32) -> f64 {
    1.0 + f64::from(percent) / 100.0
}

/// A model's ATE over a world's sequences, in order.
fn ates(world: &WorldResults, model: &str) -> Result<Vec<f64>> {
    (0..world.sequences.len())
        .map(|i| {
            let r = result(world, i, model)?;
            r.ate
                .map(|a| a.rmse)
                .with_context(|| format!("{} {model}: no ATE in its eval result", world.sequences[i].0))
        })
        .collect()
}

/// `mean [min, max]` with `digits` decimals.
fn spread(v: &[f64], digits: usize) -> String {
    let min = v.iter().copied().fold(f64::INFINITY, f64::min);
    let max = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    format!("{:.digits$} [{min:.digits$}, {max:.digits$}]", mean(v))
}

/// The mean, summed with compensation (as close to Python's `statistics.mean`, which sums
/// exactly, as a last bit).
fn mean(v: &[f64]) -> f64 {
    let (mut sum, mut compensation) = (0.0_f64, 0.0_f64);
    for &x in v {
        let t = sum + x;
        compensation += if sum.abs() >= x.abs() {
            (sum - t) + x
        } else {
            (x - t) + sum
        };
        sum = t;
    }
    (sum + compensation) / count_f64(v.len())
}

#[allow(clippy::cast_precision_loss)] // counts of runs and registrations, far below 2^52
fn count_f64(n: usize) -> f64 {
    n as f64
}

/// `text` with everything between `<!-- MARKER:begin -->` and `<!-- MARKER:end -->` replaced
/// by `content` (on lines of its own).
///
/// # Errors
/// Either marker is missing, the begin marker is there twice, or the end comes first.
pub fn replace_between_markers(text: &str, marker: &str, content: &str) -> Result<String> {
    let begin = format!("<!-- {marker}:begin -->");
    let end = format!("<!-- {marker}:end -->");
    let Some(start) = text.find(&begin) else {
        bail!("no `{begin}` marker");
    };
    if text[start + begin.len()..].contains(&begin) {
        bail!("`{begin}` is there twice");
    }
    let Some(stop) = text[start..].find(&end).map(|i| start + i) else {
        bail!("no `{end}` marker after `{begin}`");
    };
    let mut out = String::with_capacity(text.len() + content.len());
    out.push_str(&text[..start]);
    let _ = write!(out, "{begin}\n{content}\n{end}");
    out.push_str(&text[stop + end.len()..]);
    Ok(out)
}

#[cfg(test)]
mod tests {
    #[test]
    fn fifteen_percent_is_the_double_nearest_1_15() {
        assert_eq!(super::within_factor(15).to_bits(), 1.15_f64.to_bits());
    }
}
