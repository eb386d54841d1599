//! The published JSON Schemas are generated from the serde types: a change to a job, stats
//! or tag type that is not reflected in `schemas/` fails here. `UPDATE_SCHEMAS=1 cargo test
//! --release schemas` rewrites the files from the code.

use super::common::root;

#[test]
fn schemas_are_generated_from_the_code() {
    let update = std::env::var_os("UPDATE_SCHEMAS").is_some();
    let mut stale = Vec::new();
    for (file, schema) in [
        ("job.schema.json", anchorage::job::schema()),
        ("stats.schema.json", anchorage::stats::schema()),
        (
            "motion-tag.schema.json",
            anchorage::scene::MotionTag::schema(),
        ),
    ] {
        let path = root().join("schemas").join(file);
        let generated = serde_json::to_string_pretty(&schema).unwrap() + "\n";
        if update {
            std::fs::write(&path, &generated).unwrap();
        } else if std::fs::read_to_string(&path).ok().as_deref() != Some(generated.as_str()) {
            stale.push(file);
        }
    }
    assert!(
        stale.is_empty(),
        "schemas/{stale:?} differ from what the code generates; run \
         `UPDATE_SCHEMAS=1 cargo test --release schemas` and review the diff"
    );
}

/// The default the generated job schema gives `key` (a dotted path such as
/// `method.anchors.k_scale`), following `$ref`s and optional (`anyOf` with null) values.
fn schema_default(schema: &serde_json::Value, key: &str) -> Option<serde_json::Value> {
    let mut node = schema;
    let mut default = None;
    for part in key.split('.') {
        let prop = &resolve(schema, node)?["properties"][part];
        default = prop.get("default").cloned();
        node = prop;
    }
    default
}

/// `v` with `$ref`s followed and an optional value's `anyOf` reduced to its reference.
fn resolve<'a>(
    schema: &'a serde_json::Value,
    mut v: &'a serde_json::Value,
) -> Option<&'a serde_json::Value> {
    loop {
        if let Some(r) = v.get("$ref").and_then(|r| r.as_str()) {
            v = &schema["$defs"][r.trim_start_matches("#/$defs/")];
        } else if let Some(any) = v.get("anyOf").and_then(|a| a.as_array()) {
            v = any.iter().find(|x| x.get("$ref").is_some())?;
        } else {
            return Some(v);
        }
    }
}

/// Every default the README's job-file table states for a key the schema gives a default
/// (from the serde types' `Default`s) is that default: one definition per name and default.
#[test]
fn readme_key_table_states_the_code_defaults() {
    let schema = serde_json::to_value(anchorage::job::schema()).unwrap();
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    let mut checked = 0;
    for line in readme.lines().filter(|l| l.starts_with("| `")) {
        let cols: Vec<&str> = line.split(" | ").collect();
        let keys: Vec<&str> = cols[0].trim_start_matches("| ").split(", ").collect();
        let values: Vec<&str> = cols[1].split(", ").collect();
        if keys.len() != values.len() {
            continue;
        }
        let mut parent = String::new();
        for (k, v) in keys.iter().zip(values) {
            let k = k.trim_matches('`');
            let key = match k.strip_prefix('.') {
                Some(rest) => format!("{parent}.{rest}"),
                None => k.to_string(),
            };
            parent = key.rsplit_once('.').map_or("", |(p, _)| p).to_string();
            // A null default is computed elsewhere (the preset, the job file's name, ...).
            let Some(default) = schema_default(&schema, &key).filter(|d| !d.is_null()) else {
                continue;
            };
            let v = v.trim_matches('`');
            let agrees = match &default {
                // Settings are f32: compare at that precision.
                serde_json::Value::Number(n) => {
                    v.parse::<f32>().ok() == n.as_f64().map(|x| x as f32)
                }
                serde_json::Value::String(s) => v == s,
                serde_json::Value::Array(a) => {
                    v == serde_json::to_string(a).unwrap().replace(',', ", ")
                }
                _ => false,
            };
            assert!(
                agrees,
                "README says {key} defaults to {v}, the code to {default}"
            );
            checked += 1;
        }
    }
    assert!(
        checked >= 15,
        "only {checked} defaults found in the README's key table"
    );
}
