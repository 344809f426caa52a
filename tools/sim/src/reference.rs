//! The field-by-field reference of scenario files (`tools/sim/scenarios/README.md`),
//! rendered from the JSON schema so that it cannot drift from the code.

use serde_json::Value;

use crate::Scenario;

fn type_of(v: &Value) -> String {
    if let Some(r) = v.get("$ref").and_then(Value::as_str) {
        let name = r.trim_start_matches("#/$defs/");
        return format!("[{name}](#{})", name.to_lowercase());
    }
    if let Some(any) = v.get("anyOf").and_then(Value::as_array) {
        let parts: Vec<String> = any
            .iter()
            .filter(|x| x.get("type").and_then(Value::as_str) != Some("null"))
            .map(type_of)
            .collect();
        return format!("{} (optional)", parts.join(" or "));
    }
    if let Some(c) = v.get("const") {
        return format!("`{c}`");
    }
    match v.get("type") {
        Some(Value::String(t)) if t == "array" => {
            let item = v.get("items").map(type_of).unwrap_or_default();
            match (v.get("minItems"), v.get("maxItems")) {
                (Some(a), Some(b)) if a == b => format!("[{item}; {a}]"),
                _ => format!("list of {item}"),
            }
        }
        Some(Value::String(t)) => match v.get("format").and_then(Value::as_str) {
            Some("double") => "number".to_owned(),
            Some(f) if f.starts_with("uint") || f.starts_with("int") => "integer".to_owned(),
            _ => t.clone(),
        },
        Some(Value::Array(ts)) => ts.iter().filter_map(Value::as_str).collect::<Vec<_>>().join(" or "),
        _ => v
            .get("enum")
            .and_then(Value::as_array)
            .map(|e| {
                e.iter()
                    .map(|x| format!("`{}`", x.as_str().unwrap_or_default()))
                    .collect::<Vec<_>>()
                    .join(", ")
            })
            .unwrap_or_else(|| "value".to_owned()),
    }
}

fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ").replace('|', "\\|")
}

fn table(out: &mut String, obj: &Value) {
    let Some(props) = obj.get("properties").and_then(Value::as_object) else {
        return;
    };
    let required: Vec<&str> = obj
        .get("required")
        .and_then(Value::as_array)
        .map(|r| r.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    out.push_str("| field | type | default | meaning |\n|---|---|---|---|\n");
    for (name, p) in props {
        let default = match p.get("default") {
            Some(d) => format!("`{d}`"),
            None if required.contains(&name.as_str()) => "required".to_owned(),
            None => String::new(),
        };
        let doc = p.get("description").and_then(Value::as_str).unwrap_or_default();
        out.push_str(&format!(
            "| `{name}` | {} | {default} | {} |\n",
            type_of(p),
            one_line(doc)
        ));
    }
}

/// The reference as Markdown.
pub fn reference_markdown() -> String {
    let schema = serde_json::to_value(Scenario::json_schema()).unwrap_or_default();
    let mut out = String::from(
        "# Scenario files\n\n\
         Generated from the code by `GPRFLOW_UPDATE_SCHEMA=1 cargo test -p gprflow-sim --test scenarios`; \
         do not edit. Run one with `gprflow sim SCENARIO.yaml -o run.mcap [--run NAME] [--duration S] \
         [--format cmu-gpr]`; print the JSON schema with `gprflow sim --schema`.\n\n\
         Units are in the field names (`_m`, `_s`, `_hz`, `_deg`); depths are positive downwards; \
         world x east, y north, z up; body x forward, y left.\n\n## Scenario\n\n",
    );
    if let Some(d) = schema.get("description").and_then(Value::as_str) {
        out.push_str(&one_line(d));
        out.push_str("\n\n");
    }
    table(&mut out, &schema);
    if let Some(defs) = schema.get("$defs").and_then(Value::as_object) {
        for (name, def) in defs {
            out.push_str(&format!("\n## {name}\n\n"));
            if let Some(d) = def.get("description").and_then(Value::as_str) {
                out.push_str(&one_line(d));
                out.push_str("\n\n");
            }
            if let Some(variants) = def.get("oneOf").and_then(Value::as_array) {
                for v in variants {
                    let kind = v
                        .pointer("/properties/kind/const")
                        .and_then(Value::as_str)
                        .or_else(|| v.get("const").and_then(Value::as_str))
                        .unwrap_or("?");
                    let doc = v.get("description").and_then(Value::as_str).unwrap_or_default();
                    out.push_str(&format!("### `{kind}`\n\n{}\n\n", one_line(doc)));
                    table(&mut out, v);
                    out.push('\n');
                }
            } else if def.get("properties").is_some() {
                table(&mut out, def);
            } else {
                out.push_str(&format!("One of: {}.\n", type_of(def)));
            }
        }
    }
    out
}
