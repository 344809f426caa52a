//! The regression head (SPEC "Head"): a linear or nonlinear map of the correlation vector to
//! the shift, and the model's constants, read from its JSON file (serde, then one pass of
//! checks).

use std::path::Path;

use serde::de::{self, DeserializeOwned, IgnoredAny};
use serde::{Deserialize, Deserializer};
use serde_json::{Map, Value};

use super::correlation::{CorrVector, CorrelationParams};
use crate::{Error, Result};

/// The `format` of a head file.
pub const HEAD_FORMAT: &str = "gprflow-register-head";

/// The `version` of a head file this module reads.
pub const HEAD_VERSION: u64 = 1;

/// Which head a file holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeadKind {
    /// One layer, no activation.
    Linear,
    /// Hidden layers with ReLU, then a layer with one output and no activation.
    Nonlinear,
}

/// Activation of a head layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// Identity.
    None,
    /// `max(0, x)`.
    Relu,
}

/// One dense layer: `u = act(W u + b)`.
#[derive(Debug, Clone, PartialEq)]
pub struct HeadLayer {
    /// `outputs x inputs`, row-major.
    weights: Vec<f64>,
    bias: Vec<f64>,
    inputs: usize,
    activation: Activation,
}

impl HeadLayer {
    /// Outputs of the layer.
    pub fn outputs(&self) -> usize {
        self.bias.len()
    }

    /// Inputs of the layer.
    pub fn inputs(&self) -> usize {
        self.inputs
    }

    /// The layer's activation.
    pub fn activation(&self) -> Activation {
        self.activation
    }
}

/// The channel agreement check (SPEC "Do these two share features"): a pair is registered only
/// when at least `min_fraction` of the channels put their own shift `tau_k` within
/// `tolerance_m` of the head's shift.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Agreement {
    /// Largest `|tau_k - shift|` of an agreeing channel, m.
    pub tolerance_m: f64,
    /// Smallest fraction of agreeing channels, in `[0, 1]`.
    pub min_fraction: f64,
}

impl Agreement {
    /// The fraction of the channels of `corr` whose `tau_k` lies within `tolerance_m` of
    /// `shift_m`.
    pub fn fraction(&self, corr: &CorrVector, shift_m: f64) -> f64 {
        let tau = corr.tau_m();
        if tau.is_empty() {
            return 0.0;
        }
        let agreeing = tau.iter().filter(|&&t| (t - shift_m).abs() <= self.tolerance_m).count();
        agreeing as f64 / tau.len() as f64
    }
}

/// The regression head and the model's constants (SPEC "Head"), as read from its JSON file.
#[derive(Debug, Clone, PartialEq)]
pub struct Head {
    /// Linear or nonlinear.
    pub kind: HeadKind,
    /// Encoder channels, `K`.
    pub channels: usize,
    /// The encoder's stride along columns.
    pub column_stride: usize,
    /// Largest shift tried either way, m.
    pub max_shift_m: f64,
    /// Smallest shared region, as a fraction of the feature columns.
    pub min_overlap: f64,
    /// Pairs whose `mean_k m_k` is below this share no features.
    pub share_threshold: f64,
    /// The channel agreement check, when the head has one.
    pub agreement: Option<Agreement>,
    /// Robust standard deviation of the head on held-out pairs, m.
    pub sigma_m: f64,
    /// Mean target of the training pairs (the zeroth-order model), m.
    pub zeroth_m: f64,
    /// CRC-32 of the encoder file the head was fitted on, when the file names one: a head
    /// fits only its own encoder's features.
    pub encoder_crc32: Option<u32>,
    /// The file's free-form `training` record (`null` when absent).
    pub training: Value,
    mean: Vec<f64>,
    std: Vec<f64>,
    layers: Vec<HeadLayer>,
}

impl Head {
    /// Reads and checks a head file.
    ///
    /// # Errors
    /// [`Error::Io`] when the file cannot be read, [`Error::Head`] naming the field that is
    /// missing, malformed or of the wrong shape.
    pub fn from_json(path: &Path) -> Result<Head> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Head::parse(&text, path)
    }

    /// Parses and checks the text of a head file; `path` names it in errors.
    ///
    /// # Errors
    /// [`Error::Head`] naming the field that is missing, malformed or of the wrong shape.
    pub fn parse(text: &str, path: &Path) -> Result<Head> {
        let check = Check { file: path };
        let root: Value = serde_json::from_str(text).map_err(|e| check.error("(file)", format!("not JSON: {e}")))?;
        let Object(file) = Object::<HeadFile>::deserialize(&root).map_err(|e| {
            let (field, message) = culprit::<Object<HeadFile>>(&root, e);
            check.error(&field, message)
        })?;
        file.check(&check)
    }

    /// The layers, input first.
    pub fn layers(&self) -> &[HeadLayer] {
        &self.layers
    }

    /// Length of the correlation vector the head takes, `2K`.
    pub fn inputs(&self) -> usize {
        self.mean.len()
    }

    /// The predicted shift `z`, m, of the correlation vector `v` (`2K` values; extra values are
    /// ignored, missing ones count as the training mean).
    pub fn predict(&self, v: &[f64]) -> f64 {
        let widest = self.layers.iter().map(HeadLayer::outputs).max().unwrap_or(1);
        let mut buf = vec![0.0; self.inputs() + 2 * widest];
        let (u, rest) = buf.split_at_mut(self.inputs());
        for (i, x) in u.iter_mut().enumerate() {
            *x = (v.get(i).copied().unwrap_or(self.mean[i]) - self.mean[i]) / self.std[i];
        }
        let (mut a, mut b) = rest.split_at_mut(widest);
        let mut input: &[f64] = u;
        for layer in &self.layers {
            let out = &mut a[..layer.outputs()];
            for (o, y) in out.iter_mut().enumerate() {
                let row = &layer.weights[o * layer.inputs..(o + 1) * layer.inputs];
                let z = layer.bias[o] + row.iter().zip(input).map(|(w, x)| w * x).sum::<f64>();
                *y = match layer.activation {
                    Activation::None => z,
                    Activation::Relu => z.max(0.0),
                };
            }
            std::mem::swap(&mut a, &mut b);
            input = &b[..layer.outputs()];
        }
        input.first().copied().unwrap_or(self.zeroth_m)
    }

    /// The correlation parameters for submaps of `resolution_m` per column.
    pub fn correlation_params(&self, resolution_m: f64) -> CorrelationParams {
        CorrelationParams {
            column_m: resolution_m * self.column_stride as f64,
            max_shift_m: self.max_shift_m,
            min_overlap: self.min_overlap,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The file

/// A head file as written (`tools/train/SPEC.md`, "Head"). Every field may be absent here (the
/// checks, [`HeadFile::check`], say which must be there), so that a part of the file can be
/// deserialised on its own ([`culprit`]).
#[derive(Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct HeadFile {
    format: Field<String>,
    version: Field<Value>,
    kind: Field<String>,
    channels: Field<usize>,
    column_stride: Field<usize>,
    max_shift_m: Field<f64>,
    min_overlap: Field<f64>,
    normalise: Field<Object<NormaliseFile>>,
    layers: Field<Vec<Object<LayerFile>>>,
    share_threshold: Field<f64>,
    agreement: Option<Object<AgreementFile>>,
    sigma_m: Field<f64>,
    zeroth_m: Field<f64>,
    /// 8 hex digits.
    encoder_crc32: Option<String>,
    /// Free-form.
    training: Value,
}

/// `normalise`: the head takes `(v - mean) / std`.
#[derive(Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct NormaliseFile {
    mean: Field<Vec<f64>>,
    std: Field<Vec<f64>>,
}

/// One of `layers`: `weights` (`outputs` rows of `inputs`), `bias`, `activation` (`none`,
/// `relu`).
#[derive(Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct LayerFile {
    weights: Field<Vec<Vec<f64>>>,
    bias: Field<Vec<f64>>,
    activation: Field<String>,
}

/// `agreement` ([`Agreement`]).
#[derive(Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct AgreementFile {
    tolerance_m: Field<f64>,
    min_fraction: Field<f64>,
    /// How training chose `min_fraction`, in words.
    #[serde(rename = "rule")]
    _rule: IgnoredAny,
}

/// A field that may be absent. Unlike `Option`, `null` is a value, which `T` refuses (a number
/// that is `null` is no number rather than missing).
struct Field<T>(Option<T>);

impl<T> Default for Field<T> {
    fn default() -> Self {
        Field(None)
    }
}

impl<'de, T: Deserialize<'de>> Deserialize<'de> for Field<T> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        T::deserialize(d).map(|v| Field(Some(v)))
    }
}

/// A `T` written as a JSON object (serde would take a struct's fields from an array too).
struct Object<T>(T);

impl<'de, T: DeserializeOwned> Deserialize<'de> for Object<T> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let fields = Map::deserialize(d)?;
        T::deserialize(Value::Object(fields))
            .map(Object)
            .map_err(de::Error::custom)
    }
}

/// Errors naming the head file and the field.
struct Check<'a> {
    file: &'a Path,
}

impl Check<'_> {
    fn error(&self, field: &str, message: impl Into<String>) -> Error {
        Error::Head {
            file: self.file.to_path_buf(),
            field: field.to_string(),
            message: message.into(),
        }
    }

    /// A field that must be there.
    fn need<T>(&self, value: Field<T>, field: &str) -> Result<T> {
        value.0.ok_or_else(|| self.error(field, "missing"))
    }

    /// A field that must be there and be an integer >= 1.
    fn count(&self, value: Field<usize>, field: &str) -> Result<usize> {
        match self.need(value, field)? {
            0 => Err(self.error(field, "expected an integer >= 1, got 0")),
            n => Ok(n),
        }
    }

    /// A number that must be there and be `ok` (`expected` says how).
    fn number(&self, value: Field<f64>, field: &str, ok: impl Fn(f64) -> bool, expected: &str) -> Result<f64> {
        let x = self.need(value, field)?;
        if ok(x) {
            Ok(x)
        } else {
            Err(self.error(field, format!("{x}, expected {expected}")))
        }
    }

    /// `values`, which must be `len`.
    fn numbers(&self, values: Vec<f64>, field: &str, len: usize) -> Result<Vec<f64>> {
        if values.len() != len {
            return Err(self.error(field, format!("{} values, expected {len}", values.len())));
        }
        Ok(values)
    }
}

impl HeadFile {
    /// The head the file holds: every field there that must be, the sizes fitting together
    /// (`2 channels` inputs, layer after layer), the numbers in range.
    fn check(self, check: &Check<'_>) -> Result<Head> {
        let format = check.need(self.format, "format")?;
        if format != HEAD_FORMAT {
            return Err(check.error("format", format!("{format:?}, expected {HEAD_FORMAT:?}")));
        }
        let version = check.need(self.version, "version")?;
        if version.as_u64() != Some(HEAD_VERSION) {
            return Err(check.error("version", format!("{version}, this reader knows {HEAD_VERSION}")));
        }
        let kind = match check.need(self.kind, "kind")?.as_str() {
            "linear" => HeadKind::Linear,
            "nonlinear" => HeadKind::Nonlinear,
            other => return Err(check.error("kind", format!("{other:?}, expected \"linear\" or \"nonlinear\""))),
        };
        let channels = check.count(self.channels, "channels")?;
        let column_stride = check.count(self.column_stride, "column_stride")?;
        let max_shift_m = check.number(self.max_shift_m, "max_shift_m", |x| x >= 0.0, ">= 0")?;
        let min_overlap = check.number(self.min_overlap, "min_overlap", |x| x > 0.0 && x <= 1.0, "in (0, 1]")?;
        let inputs = 2 * channels;
        let Object(normalise) = check.need(self.normalise, "normalise")?;
        let mean = check.numbers(check.need(normalise.mean, "normalise.mean")?, "normalise.mean", inputs)?;
        let std = check.numbers(check.need(normalise.std, "normalise.std")?, "normalise.std", inputs)?;
        if let Some(i) = std.iter().position(|&s| s <= 0.0) {
            return Err(check.error(&format!("normalise.std[{i}]"), format!("{}, expected > 0", std[i])));
        }
        let layers = check_layers(check, check.need(self.layers, "layers")?, kind, inputs)?;
        let share_threshold = check.need(self.share_threshold, "share_threshold")?;
        let agreement = match self.agreement {
            Some(Object(agreement)) => Some(agreement.check(check)?),
            None => None,
        };
        let sigma_m = check.number(self.sigma_m, "sigma_m", |x| x > 0.0, "> 0")?;
        let zeroth_m = check.need(self.zeroth_m, "zeroth_m")?;
        let encoder_crc32 = match self.encoder_crc32 {
            Some(text) => {
                let parsed = (text.len() == 8).then(|| u32::from_str_radix(&text, 16).ok()).flatten();
                Some(parsed.ok_or_else(|| check.error("encoder_crc32", format!("{text:?}, expected 8 hex digits")))?)
            }
            None => None,
        };
        Ok(Head {
            kind,
            channels,
            column_stride,
            max_shift_m,
            min_overlap,
            share_threshold,
            agreement,
            sigma_m,
            zeroth_m,
            encoder_crc32,
            training: self.training,
            mean,
            std,
            layers,
        })
    }
}

/// The layers of a `kind` head taking `inputs` values: a linear head has one, a nonlinear head
/// hidden ones (ReLU) too; the last has one output and no activation.
fn check_layers(
    check: &Check<'_>,
    items: Vec<Object<LayerFile>>,
    kind: HeadKind,
    inputs: usize,
) -> Result<Vec<HeadLayer>> {
    match (kind, items.len()) {
        (_, 0) => return Err(check.error("layers", "empty")),
        (HeadKind::Linear, n) if n != 1 => {
            return Err(check.error("layers", format!("{n} layers, a linear head has 1")));
        }
        (HeadKind::Nonlinear, 1) => {
            return Err(check.error("layers", "1 layer, a nonlinear head has hidden layers"));
        }
        _ => {}
    }
    let count = items.len();
    let mut layers = Vec::with_capacity(count);
    let mut width = inputs;
    for (i, Object(layer)) in items.into_iter().enumerate() {
        let field = |key: &str| format!("layers[{i}].{key}");
        let last = i + 1 == count;
        let activation = match check.need(layer.activation, &field("activation"))?.as_str() {
            "none" => Activation::None,
            "relu" => Activation::Relu,
            other => {
                return Err(check.error(
                    &field("activation"),
                    format!("{other:?}, expected \"none\" or \"relu\""),
                ));
            }
        };
        let expected = if last { Activation::None } else { Activation::Relu };
        if activation != expected {
            return Err(check.error(
                &field("activation"),
                format!(
                    "{activation:?}, expected {expected:?} ({})",
                    if last { "the output layer" } else { "a hidden layer" }
                ),
            ));
        }
        let rows = check.need(layer.weights, &field("weights"))?;
        let bias = check.need(layer.bias, &field("bias"))?;
        let outputs = if last { 1 } else { bias.len() };
        if outputs == 0 {
            return Err(check.error(&field("bias"), "expected a non-empty array"));
        }
        if rows.len() != outputs {
            return Err(check.error(&field("weights"), format!("{} rows, expected {outputs}", rows.len())));
        }
        let bias = check.numbers(bias, &field("bias"), outputs)?;
        let mut weights = Vec::with_capacity(outputs * width);
        for (r, row) in rows.into_iter().enumerate() {
            weights.extend(check.numbers(row, &format!("{}[{r}]", field("weights")), width)?);
        }
        layers.push(HeadLayer {
            weights,
            bias,
            inputs: width,
            activation,
        });
        width = outputs;
    }
    Ok(layers)
}

impl AgreementFile {
    fn check(self, check: &Check<'_>) -> Result<Agreement> {
        let tolerance_m = check.number(self.tolerance_m, "agreement.tolerance_m", |x| x > 0.0, "> 0")?;
        let min_fraction = check.number(
            self.min_fraction,
            "agreement.min_fraction",
            |x| (0.0..=1.0).contains(&x),
            "in [0, 1]",
        )?;
        Ok(Agreement {
            tolerance_m,
            min_fraction,
        })
    }
}

/// A step down a JSON value.
enum Step<'v> {
    Key(&'v str),
    Index(usize),
}

/// Where and why `root` does not deserialise as a `T` (`error`): its path (`layers[0].bias`,
/// `(file)` for the root) and the message in this file's words ([`reworded`]). serde names a
/// field that is unknown but not one whose value has the wrong type, so the part at fault is
/// found by deserialising `root` cut down to one branch (every field of `T` may be absent):
/// from the root down, the first child that fails on its own, until a value that fails with
/// none of its children (or empty, when it is an object or an array of the wrong kind).
fn culprit<T: DeserializeOwned>(root: &Value, mut error: serde_json::Error) -> (String, String) {
    // `node` at the end of `path`, and nothing else
    let fails = |path: &[Step<'_>], node: Value| {
        let branch = path.iter().rev().fold(node, |v, step| match step {
            Step::Key(k) => Value::Object(Map::from_iter([(k.to_string(), v)])),
            Step::Index(_) => Value::Array(vec![v]),
        });
        T::deserialize(&branch).err()
    };
    let mut path = Vec::new();
    let mut node = root;
    'down: loop {
        let children: Vec<(Step<'_>, &Value)> = match node {
            Value::Object(m) if fails(&path, Value::Object(Map::new())).is_none() => {
                m.iter().map(|(k, v)| (Step::Key(k), v)).collect()
            }
            Value::Array(a) if fails(&path, Value::Array(Vec::new())).is_none() => {
                a.iter().enumerate().map(|(i, v)| (Step::Index(i), v)).collect()
            }
            _ => Vec::new(),
        };
        for (step, child) in children {
            path.push(step);
            if let Some(e) = fails(&path, child.clone()) {
                (error, node) = (e, child);
                continue 'down;
            }
            path.pop();
        }
        break;
    }
    let mut field = String::new();
    for step in &path {
        match step {
            Step::Key(k) if field.is_empty() => field.push_str(k),
            Step::Key(k) => field.push_str(&format!(".{k}")),
            Step::Index(i) => field.push_str(&format!("[{i}]")),
        }
    }
    if field.is_empty() {
        field.push_str("(file)");
    }
    (field, reworded(&error.to_string(), node))
}

/// serde's "invalid type: map, expected a sequence" in this file's words: "expected an array,
/// got an object" (`node`: the value at fault).
fn reworded(message: &str, node: &Value) -> String {
    let expected = ["invalid type: ", "invalid value: "]
        .into_iter()
        .find_map(|prefix| message.strip_prefix(prefix))
        .and_then(|rest| rest.split_once(", expected "));
    let Some((_, expected)) = expected else {
        return message.to_string();
    };
    let expected = match expected {
        "a sequence" => "an array",
        "a map" => "an object",
        "f64" => "a finite number",
        "usize" => "an integer >= 1",
        other => other,
    };
    format!("expected {expected}, got {}", kind_of(node))
}

/// A value as the messages name it.
fn kind_of(value: &Value) -> String {
    match value {
        Value::Null => "null".into(),
        Value::Bool(b) => format!("{b}"),
        Value::Number(n) => format!("{n}"),
        Value::String(s) => format!("{s:?}"),
        Value::Array(a) => format!("an array of {}", a.len()),
        Value::Object(_) => "an object".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn head_json(kind: &str, layers: &str) -> String {
        format!(
            r#"{{ "format": "gprflow-register-head", "version": 1, "kind": "{kind}",
                "channels": 2, "column_stride": 4, "max_shift_m": 1.5, "min_overlap": 0.5,
                "normalise": {{ "mean": [0, 0, 0.5, 0.5], "std": [1, 1, 0.5, 0.5] }},
                "layers": {layers},
                "share_threshold": 0.3, "sigma_m": 0.05, "zeroth_m": 0.1,
                "training": {{ "pairs": 10 }} }}"#
        )
    }

    #[test]
    fn heads_predict_their_layers() {
        let path = Path::new("h.json");
        let linear = Head::parse(
            &head_json(
                "linear",
                r#"[{"weights": [[0.5, 0.5, 0, 1]], "bias": [0.25], "activation": "none"}]"#,
            ),
            path,
        )
        .expect("valid");
        // u = [1, 3, 1, -1]
        assert!((linear.predict(&[1.0, 3.0, 1.0, 0.0]) - (0.25 + 0.5 + 1.5 - 1.0)).abs() < 1e-15);
        let nonlinear = Head::parse(
            &head_json(
                "nonlinear",
                r#"[{"weights": [[1, 0, 0, 0], [-1, 0, 0, 0]], "bias": [0, 0], "activation": "relu"},
                    {"weights": [[2, 3]], "bias": [-1], "activation": "none"}]"#,
            ),
            path,
        )
        .expect("valid");
        assert_eq!(nonlinear.predict(&[2.0, 0.0, 0.5, 0.5]), 2.0 * 2.0 - 1.0);
        assert_eq!(nonlinear.predict(&[-2.0, 0.0, 0.5, 0.5]), 3.0 * 2.0 - 1.0);
        assert_eq!(nonlinear.training["pairs"], 10);
    }

    #[test]
    fn the_agreement_check_counts_the_channels_near_the_shift() {
        let corr = CorrVector {
            values: vec![0.10, 0.12, 0.50, -0.30, 0.9, 0.9, 0.9, 0.9],
            max_shift_cols: 10,
        };
        let check = Agreement {
            tolerance_m: 0.05,
            min_fraction: 0.5,
        };
        assert_eq!(check.fraction(&corr, 0.11), 0.5);
        assert_eq!(check.fraction(&corr, 0.52), 0.25);
        assert_eq!(check.fraction(&corr, 2.0), 0.0);
        let path = Path::new("h.json");
        let one = r#"[{"weights": [[0.5, 0.5, 0, 1]], "bias": [0.25], "activation": "none"}]"#;
        let with = head_json("linear", one).replace(
            "\"share_threshold\": 0.3",
            "\"share_threshold\": 0.3, \"agreement\": {\"tolerance_m\": 0.05, \"min_fraction\": 0.5, \"rule\": \"r\"}",
        );
        assert_eq!(Head::parse(&with, path).expect("valid").agreement, Some(check));
        assert_eq!(
            Head::parse(&head_json("linear", one), path).expect("valid").agreement,
            None
        );
    }

    #[test]
    fn malformed_heads_name_the_file_and_the_field() {
        let path = Path::new("models/ground_encoding.head.json");
        let one = r#"[{"weights": [[0.5, 0.5, 0, 1]], "bias": [0.25], "activation": "none"}]"#;
        let cases = [
            (
                head_json(
                    "linear",
                    r#"[{"weights": [[1,1,1,1],[1,1,1,1],[1,1,1,1]], "bias": [0], "activation": "none"}]"#,
                ),
                "ground_encoding.head.json: layers[0].weights: 3 rows, expected 1",
            ),
            (
                head_json(
                    "linear",
                    r#"[{"weights": [[1,1,1]], "bias": [0], "activation": "none"}]"#,
                ),
                "layers[0].weights[0]: 3 values, expected 4",
            ),
            (
                head_json(
                    "linear",
                    r#"[{"weights": [[1,1,1,1]], "bias": [0], "activation": "relu"}]"#,
                ),
                "layers[0].activation: Relu, expected None",
            ),
            (head_json("nonlinear", one), "layers: 1 layer"),
            (head_json("cubic", one), "kind: \"cubic\""),
            (head_json("linear", "{}"), "layers: expected an array"),
            (
                head_json("linear", one).replace("\"version\": 1", "\"version\": 2"),
                "version: 2",
            ),
            (
                head_json("linear", one).replace("[1, 1, 0.5, 0.5]", "[1, 0, 0.5, 0.5]"),
                "normalise.std[1]: 0",
            ),
            (
                head_json("linear", one).replace("[0, 0, 0.5, 0.5]", "[0, 0, 0.5]"),
                "normalise.mean: 3 values, expected 4",
            ),
            (
                head_json("linear", one).replace("\"sigma_m\": 0.05,", ""),
                "sigma_m: missing",
            ),
            (
                head_json("linear", one).replace("\"channels\": 2", "\"channels\": 0"),
                "channels: expected an integer >= 1",
            ),
            (
                head_json("linear", one).replace("\"zeroth_m\"", "\"zeroth\""),
                "zeroth: unknown field",
            ),
            (
                head_json("linear", one).replace("\"share_threshold\": 0.3", "\"share_threshold\": \"x\""),
                "share_threshold: expected a finite number",
            ),
            (
                head_json("linear", one).replace(
                    "\"share_threshold\": 0.3",
                    "\"share_threshold\": 0.3, \"agreement\": {\"tolerance_m\": 0.05, \"min_fraction\": 1.5}",
                ),
                "agreement.min_fraction: 1.5, expected in [0, 1]",
            ),
            (
                head_json("linear", one).replace(
                    "\"share_threshold\": 0.3",
                    "\"share_threshold\": 0.3, \"agreement\": {\"min_fraction\": 0.5}",
                ),
                "agreement.tolerance_m: missing",
            ),
            (
                head_json("linear", one).replace(
                    "\"share_threshold\": 0.3",
                    "\"share_threshold\": 0.3, \"agreement\": {\"tolerance_m\": 0.05, \"min_fraction\": 0.5, \"x\": 1}",
                ),
                "agreement.x: unknown field",
            ),
            (
                head_json("linear", one)
                    .replace("\"zeroth_m\": 0.1", "\"zeroth_m\": 0.1, \"encoder_crc32\": \"12345\""),
                "encoder_crc32: \"12345\", expected 8 hex digits",
            ),
            (
                head_json("linear", one).replace(
                    "\"zeroth_m\": 0.1",
                    "\"zeroth_m\": 0.1, \"encoder_crc32\": \"1234567g\"",
                ),
                "encoder_crc32: \"1234567g\", expected 8 hex digits",
            ),
            ("[1, 2".to_string(), "(file): not JSON"),
            ("[]".to_string(), "(file): expected an object"),
        ];
        for (text, want) in cases {
            let e = Head::parse(&text, path).expect_err(want);
            assert!(matches!(e, Error::Head { .. }), "{e:?}");
            let msg = e.to_string();
            assert!(msg.starts_with("models/ground_encoding.head.json: "), "{msg}");
            assert!(msg.contains(want), "{msg}\n  wanted: {want}");
        }
    }

    #[test]
    fn what_serde_alone_would_take_or_leave_unnamed_is_refused_with_its_field() {
        // serde takes a struct from an array, `null` for an absent `Option`, and names no field
        // in a type error
        let path = Path::new("h.json");
        let one = r#"[{"weights": [[0.5, 0.5, 0, 1]], "bias": [0.25], "activation": "none"}]"#;
        let cases = [
            (
                head_json("linear", one).replace("\"zeroth_m\": 0.1", "\"zeroth_m\": 0.1, \"agreement\": [0.05, 0.5]"),
                "h.json: agreement: expected an object, got an array of 2",
            ),
            (
                head_json("linear", r#"[[[[0.5, 0.5, 0, 1]], [0.25], "none"]]"#),
                "h.json: layers[0]: expected an object, got an array of 3",
            ),
            (
                head_json("linear", one).replace("\"sigma_m\": 0.05", "\"sigma_m\": null"),
                "h.json: sigma_m: expected a finite number, got null",
            ),
            (
                head_json("linear", one).replace("\"channels\": 2", "\"channels\": 1.5"),
                "h.json: channels: expected an integer >= 1, got 1.5",
            ),
            (
                head_json("linear", one).replace("\"channels\": 2", "\"channels\": -2"),
                "h.json: channels: expected an integer >= 1, got -2",
            ),
            (
                head_json("linear", one).replace("[1, 1, 0.5, 0.5]", "[1, \"1\", 0.5, 0.5]"),
                "h.json: normalise.std[1]: expected a finite number, got \"1\"",
            ),
            (
                head_json("linear", one).replace("[[0.5, 0.5, 0, 1]]", "[[0.5, 0.5, 0, {}]]"),
                "h.json: layers[0].weights[0][3]: expected a finite number, got an object",
            ),
            (
                head_json("linear", one).replace(
                    "\"activation\": \"none\"",
                    "\"activation\": \"none\", \"x\": {\"y\": 1}",
                ),
                "h.json: layers[0].x: unknown field",
            ),
            (
                head_json("linear", one).replace("\"zeroth_m\": 0.1", "\"zeroth_m\": 0.1, \"encoder_crc32\": 5"),
                "h.json: encoder_crc32: expected a string, got 5",
            ),
        ];
        for (text, want) in cases {
            let e = Head::parse(&text, path).expect_err(want);
            assert!(matches!(e, Error::Head { .. }), "{e:?}");
            assert!(e.to_string().starts_with(want), "{e}\n  wanted: {want}");
        }
        // and `null` where an optional part may be absent is absent, as before
        let text = head_json("linear", one).replace(
            "\"zeroth_m\": 0.1",
            "\"zeroth_m\": 0.1, \"agreement\": null, \"encoder_crc32\": null",
        );
        let head = Head::parse(&text, path).expect("valid");
        assert_eq!((head.agreement, head.encoder_crc32), (None, None));
    }

    proptest::proptest! {
        #[test]
        fn head_parsing_never_panics(text in ".{0,200}") {
            let _ = Head::parse(&text, Path::new("x.json"));
        }

    }
}
