//! Integration tests, one binary (STYLE.md §10). Third-party scenes are read from
//! `../shared/scenes/` or `$ANCHORAGE_SCENES`, through `common::shared_scene`
//! (`tests/scenes/manifest.tsv` lists them; `scripts/fetch-scenes.sh` fetches them). The
//! Python checks (OpenEXR, usd-core, usd2gltf) use the virtual environment that `.ci/run`
//! creates in `.venv`.

mod it;
