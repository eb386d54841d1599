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
