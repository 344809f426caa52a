//! The regression head (SPEC "Head"): a linear or nonlinear map of the correlation vector to
//! the shift, and the model's constants, read from its JSON file.

use std::path::Path;

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
    fn parse(rd: &HeadReader<'_>, value: &Value) -> Result<Agreement> {
        let obj = rd.object(value, "agreement")?;
        rd.only_keys(obj, "agreement", &["tolerance_m", "min_fraction", "rule"])?;
        let tolerance_m = rd.number(rd.field(obj, "agreement", "tolerance_m")?, "agreement.tolerance_m")?;
        if tolerance_m <= 0.0 {
            return Err(rd.error("agreement.tolerance_m", format!("{tolerance_m}, expected > 0")));
        }
        let min_fraction = rd.number(rd.field(obj, "agreement", "min_fraction")?, "agreement.min_fraction")?;
        if !(0.0..=1.0).contains(&min_fraction) {
            return Err(rd.error("agreement.min_fraction", format!("{min_fraction}, expected in [0, 1]")));
        }
        Ok(Agreement {
            tolerance_m,
            min_fraction,
        })
    }

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

/// Reads the fields of a head file, each error naming the file and the field.
struct HeadReader<'a> {
    file: &'a Path,
}

impl HeadReader<'_> {
    fn error(&self, field: &str, message: impl Into<String>) -> Error {
        Error::Head {
            file: self.file.to_path_buf(),
            field: field.to_string(),
            message: message.into(),
        }
    }

    fn object<'v>(&self, value: &'v Value, field: &str) -> Result<&'v Map<String, Value>> {
        value
            .as_object()
            .ok_or_else(|| self.error(field, format!("expected an object, got {}", kind_of(value))))
    }

    fn field<'v>(&self, obj: &'v Map<String, Value>, prefix: &str, key: &str) -> Result<&'v Value> {
        obj.get(key).ok_or_else(|| self.error(&join(prefix, key), "missing"))
    }

    fn only_keys(&self, obj: &Map<String, Value>, prefix: &str, known: &[&str]) -> Result<()> {
        match obj.keys().find(|k| !known.contains(&k.as_str())) {
            Some(k) => Err(self.error(&join(prefix, k), format!("unknown field (known: {})", known.join(", ")))),
            None => Ok(()),
        }
    }

    fn string<'v>(&self, value: &'v Value, field: &str) -> Result<&'v str> {
        value
            .as_str()
            .ok_or_else(|| self.error(field, format!("expected a string, got {}", kind_of(value))))
    }

    fn number(&self, value: &Value, field: &str) -> Result<f64> {
        match value.as_f64() {
            Some(x) if x.is_finite() => Ok(x),
            _ => Err(self.error(field, format!("expected a finite number, got {}", kind_of(value)))),
        }
    }

    fn count(&self, value: &Value, field: &str) -> Result<usize> {
        match value.as_u64().and_then(|n| usize::try_from(n).ok()) {
            Some(n) if n > 0 => Ok(n),
            _ => Err(self.error(field, format!("expected an integer >= 1, got {value}"))),
        }
    }

    fn numbers(&self, value: &Value, field: &str, len: usize) -> Result<Vec<f64>> {
        let items = value
            .as_array()
            .ok_or_else(|| self.error(field, format!("expected an array, got {}", kind_of(value))))?;
        if items.len() != len {
            return Err(self.error(field, format!("{} values, expected {len}", items.len())));
        }
        items
            .iter()
            .enumerate()
            .map(|(i, v)| self.number(v, &format!("{field}[{i}]")))
            .collect()
    }
}

fn join(prefix: &str, key: &str) -> String {
    if prefix.is_empty() {
        key.to_string()
    } else {
        format!("{prefix}.{key}")
    }
}

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

const HEAD_KEYS: &[&str] = &[
    "format",
    "version",
    "kind",
    "channels",
    "column_stride",
    "max_shift_m",
    "min_overlap",
    "normalise",
    "layers",
    "share_threshold",
    "agreement",
    "sigma_m",
    "zeroth_m",
    "encoder_crc32",
    "training",
];

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
        let rd = HeadReader { file: path };
        let root: Value = serde_json::from_str(text).map_err(|e| rd.error("(file)", format!("not JSON: {e}")))?;
        let obj = rd.object(&root, "(file)")?;
        rd.only_keys(obj, "", HEAD_KEYS)?;
        let format = rd.string(rd.field(obj, "", "format")?, "format")?;
        if format != HEAD_FORMAT {
            return Err(rd.error("format", format!("{format:?}, expected {HEAD_FORMAT:?}")));
        }
        let version = rd.field(obj, "", "version")?;
        if version.as_u64() != Some(HEAD_VERSION) {
            return Err(rd.error("version", format!("{version}, this reader knows {HEAD_VERSION}")));
        }
        let kind = match rd.string(rd.field(obj, "", "kind")?, "kind")? {
            "linear" => HeadKind::Linear,
            "nonlinear" => HeadKind::Nonlinear,
            other => return Err(rd.error("kind", format!("{other:?}, expected \"linear\" or \"nonlinear\""))),
        };
        let channels = rd.count(rd.field(obj, "", "channels")?, "channels")?;
        let column_stride = rd.count(rd.field(obj, "", "column_stride")?, "column_stride")?;
        let max_shift_m = rd.number(rd.field(obj, "", "max_shift_m")?, "max_shift_m")?;
        if max_shift_m < 0.0 {
            return Err(rd.error("max_shift_m", format!("{max_shift_m}, expected >= 0")));
        }
        let min_overlap = rd.number(rd.field(obj, "", "min_overlap")?, "min_overlap")?;
        if !(min_overlap > 0.0 && min_overlap <= 1.0) {
            return Err(rd.error("min_overlap", format!("{min_overlap}, expected in (0, 1]")));
        }
        let inputs = 2 * channels;
        let normalise = rd.object(rd.field(obj, "", "normalise")?, "normalise")?;
        rd.only_keys(normalise, "normalise", &["mean", "std"])?;
        let mean = rd.numbers(rd.field(normalise, "normalise", "mean")?, "normalise.mean", inputs)?;
        let std = rd.numbers(rd.field(normalise, "normalise", "std")?, "normalise.std", inputs)?;
        if let Some(i) = std.iter().position(|&s| s <= 0.0) {
            return Err(rd.error(&format!("normalise.std[{i}]"), format!("{}, expected > 0", std[i])));
        }
        let layers = Head::parse_layers(&rd, rd.field(obj, "", "layers")?, kind, inputs)?;
        let share_threshold = rd.number(rd.field(obj, "", "share_threshold")?, "share_threshold")?;
        let agreement = match obj.get("agreement") {
            None | Some(Value::Null) => None,
            Some(value) => Some(Agreement::parse(&rd, value)?),
        };
        let sigma_m = rd.number(rd.field(obj, "", "sigma_m")?, "sigma_m")?;
        if sigma_m <= 0.0 {
            return Err(rd.error("sigma_m", format!("{sigma_m}, expected > 0")));
        }
        let zeroth_m = rd.number(rd.field(obj, "", "zeroth_m")?, "zeroth_m")?;
        let encoder_crc32 = match obj.get("encoder_crc32") {
            None | Some(Value::Null) => None,
            Some(value) => {
                let text = rd.string(value, "encoder_crc32")?;
                let parsed = (text.len() == 8).then(|| u32::from_str_radix(text, 16).ok()).flatten();
                Some(parsed.ok_or_else(|| rd.error("encoder_crc32", format!("{text:?}, expected 8 hex digits")))?)
            }
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
            training: obj.get("training").cloned().unwrap_or(Value::Null),
            mean,
            std,
            layers,
        })
    }

    fn parse_layers(rd: &HeadReader<'_>, value: &Value, kind: HeadKind, inputs: usize) -> Result<Vec<HeadLayer>> {
        let items = value
            .as_array()
            .ok_or_else(|| rd.error("layers", format!("expected an array, got {}", kind_of(value))))?;
        match (kind, items.len()) {
            (_, 0) => return Err(rd.error("layers", "empty")),
            (HeadKind::Linear, n) if n != 1 => {
                return Err(rd.error("layers", format!("{n} layers, a linear head has 1")));
            }
            (HeadKind::Nonlinear, 1) => {
                return Err(rd.error("layers", "1 layer, a nonlinear head has hidden layers"));
            }
            _ => {}
        }
        let mut layers = Vec::with_capacity(items.len());
        let mut width = inputs;
        for (i, item) in items.iter().enumerate() {
            let field = format!("layers[{i}]");
            let obj = rd.object(item, &field)?;
            rd.only_keys(obj, &field, &["weights", "bias", "activation"])?;
            let last = i + 1 == items.len();
            let activation = match rd.string(rd.field(obj, &field, "activation")?, &join(&field, "activation"))? {
                "none" => Activation::None,
                "relu" => Activation::Relu,
                other => {
                    return Err(rd.error(
                        &join(&field, "activation"),
                        format!("{other:?}, expected \"none\" or \"relu\""),
                    ));
                }
            };
            let expected = if last { Activation::None } else { Activation::Relu };
            if activation != expected {
                return Err(rd.error(
                    &join(&field, "activation"),
                    format!(
                        "{activation:?}, expected {expected:?} ({})",
                        if last { "the output layer" } else { "a hidden layer" }
                    ),
                ));
            }
            let weights_field = join(&field, "weights");
            let rows = rd.field(obj, &field, "weights")?;
            let rows = rows.as_array().ok_or_else(|| {
                rd.error(
                    &weights_field,
                    format!("expected an array of rows, got {}", kind_of(rows)),
                )
            })?;
            let bias_value = rd.field(obj, &field, "bias")?;
            let outputs = if last {
                1
            } else {
                bias_value.as_array().map_or(0, Vec::len)
            };
            if outputs == 0 {
                return Err(rd.error(&join(&field, "bias"), "expected a non-empty array"));
            }
            if rows.len() != outputs {
                return Err(rd.error(&weights_field, format!("{} rows, expected {outputs}", rows.len())));
            }
            let bias = rd.numbers(bias_value, &join(&field, "bias"), outputs)?;
            let mut weights = Vec::with_capacity(outputs * width);
            for (r, row) in rows.iter().enumerate() {
                weights.extend(rd.numbers(row, &format!("{weights_field}[{r}]"), width)?);
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

    proptest::proptest! {
        #[test]
        fn head_parsing_never_panics(text in ".{0,200}") {
            let _ = Head::parse(&text, Path::new("x.json"));
        }

    }
}
